"""golden_support.expect_golden: this machine's entry is enforced; a machine with none is skipped."""

from __future__ import annotations

import golden_support
import pytest
from golden_support import RECORDED_BEFORE_FINGERPRINTS, expect_golden, machine_fingerprint


def test_fingerprint_is_stable_and_names_the_cpu_features(monkeypatch: pytest.MonkeyPatch) -> None:
    first = machine_fingerprint()
    assert first == machine_fingerprint() and len(first) == 16
    features = dict(golden_support.__cpu_features__)
    flipped = next(name for name, enabled in features.items() if enabled)
    monkeypatch.setattr(golden_support, "__cpu_features__", {**features, flipped: False})
    assert machine_fingerprint() != first


def test_this_machines_entry_is_enforced() -> None:
    here = machine_fingerprint()
    expect_golden(("a",), {here: ("a",)}, generate="x")
    with pytest.raises(AssertionError):
        expect_golden(("b",), {here: ("a",), RECORDED_BEFORE_FINGERPRINTS: ("b",)}, generate="x")


def test_a_machine_without_an_entry_uses_the_first_digests_or_skips() -> None:
    expect_golden(("old",), {"elsewhere": ("new",), RECORDED_BEFORE_FINGERPRINTS: ("old",)}, generate="x")
    with pytest.raises(pytest.skip.Exception, match=r"no golden digests for machine .* with golden_support\.x"):
        expect_golden(("other",), {RECORDED_BEFORE_FINGERPRINTS: ("old",)}, generate="golden_support.x")
