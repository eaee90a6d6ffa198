"""Moved to :mod:`capevo.records.names`; this alias goes once every import names the new home."""

from capevo.records.names import *  # noqa: F403
