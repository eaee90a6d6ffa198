"""Builds the C parts (the fused governance kernel, the trace writer's hot path); everything else
about the package is in pyproject.toml."""

from pathlib import Path

from setuptools import Extension, setup

CSRC = Path("capevo/runtime/governance/csrc")
TRACES_CSRC = Path("capevo/runtime/traces/csrc")
C_FLAGS = ["-O2", "-std=c11", "-Wall"]

setup(
    ext_modules=[
        Extension(
            "capevo.runtime.governance._fused",
            sources=sorted(str(p) for p in CSRC.glob("*.c")),
            depends=[str(CSRC / "kernel.h")],
            # Bit-for-bit the Python checks' arithmetic: no fused multiply-add, no fast-math.
            extra_compile_args=[
                "-O2",
                "-ffp-contract=off",
                "-fno-fast-math",
                "-std=c11",
                "-Wall",
                "-Wno-unused-function",
            ],
        ),
        # The trace writer's hot path: its queue, the rows' splicer, MCAP framing and input packing
        # (queue.py, codec.py, mcapfile.py and rows.py have the Python versions they follow).
        Extension(
            "capevo.runtime.traces._native",
            sources=sorted(str(p) for p in TRACES_CSRC.glob("*.c")),
            depends=[str(TRACES_CSRC / "traces.h")],
            extra_compile_args=C_FLAGS,
        ),
    ]
)
