"""``mrta-bench`` as a script: same code (mrta_rl/commands/bench.py), same arguments."""

from __future__ import annotations

from mrta_rl.commands.bench import main

if __name__ == "__main__":
    main()
