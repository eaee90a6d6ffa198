"""The experiment harness (issue 20, paper §4): grids of tasks × methods × seeds run as Ray tasks,
``capevo experiment run|report|verify``."""

from __future__ import annotations
