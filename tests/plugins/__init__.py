"""Learners outside the package, as a user writes them (tests/learners/test_plugin_learner.py)."""
