"""The shipped configs, installed as the package ``mrta_rl.conf`` (pyproject.toml maps it here)."""
