"""Moved to :mod:`capevo.records.audit`; this alias goes once every import names the new home."""

from capevo.records.audit import *  # noqa: F403
