"""Moved to :mod:`capevo.records.lifecycle`; this alias goes once every import names the new home."""

from capevo.records.lifecycle import *  # noqa: F403
