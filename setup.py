"""Builds the fused governance kernel; everything else about the package is in pyproject.toml."""

from pathlib import Path

from setuptools import Extension, setup

CSRC = Path("capevo/runtime/governance/csrc")

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
        )
    ]
)
