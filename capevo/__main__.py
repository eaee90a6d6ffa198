"""``python -m capevo``: the same command line as the ``capevo`` console script."""

from __future__ import annotations

from capevo.cli import main

if __name__ == "__main__":
    main(prog_name="capevo")
