"""``mrta-partition`` as a script: same code (mrta_rl/commands/partition.py), same arguments."""

from __future__ import annotations

from mrta_rl.commands.partition import main

if __name__ == "__main__":
    main()
