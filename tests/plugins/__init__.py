"""Learners outside the package, as a user writes them (tests/smoke/test_plugin_learner.py)."""
