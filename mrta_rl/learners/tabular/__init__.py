"""Tabular Q-learners (paper eq. 3): subG-CQL, CQL, semi-CQL, DQL, on the batched auction env."""

from __future__ import annotations
