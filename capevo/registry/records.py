"""Moved to :mod:`capevo.records`; this alias goes once every import names the new home."""

from capevo.records import *  # noqa: F403
