"""``mrta-report`` as a script: same code (mrta_rl/commands/report.py), same arguments."""

from __future__ import annotations

from mrta_rl.commands.report import main

if __name__ == "__main__":
    main()
