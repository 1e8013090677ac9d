"""``mrta-train`` as a script: same code (mrta_rl/commands/train.py), same arguments."""

from __future__ import annotations

from mrta_rl.commands.train import main

if __name__ == "__main__":
    main()
