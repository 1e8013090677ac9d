"""``mrta-evaluate`` as a script: same code (mrta_rl/commands/evaluate.py), same arguments."""

from __future__ import annotations

from mrta_rl.commands.evaluate import main

if __name__ == "__main__":
    main()
