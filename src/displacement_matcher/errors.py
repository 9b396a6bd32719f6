"""Errors raised by the displacement matcher package."""

from __future__ import annotations


class MatcherError(ValueError):
    """An input to the displacement matcher is malformed (bad pose set, unit map or parameter)."""
