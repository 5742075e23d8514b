"""The fixture that ends, after every test, every process the test started (imported by conftest)."""

from __future__ import annotations

import warnings

import pytest
from processes import TAG_VARIABLE, kill_tagged, new_tag


@pytest.fixture(autouse=True)
def no_process_outlives_its_test(monkeypatch):
    """Tag this test's environment: whatever it starts, by any means, inherits the tag and is
    killed when the test ends, passed, failed or timed out (pytest-timeout fails it first)."""
    tag = new_tag()
    monkeypatch.setenv(TAG_VARIABLE, tag)
    yield
    left = kill_tagged(tag)
    if left:
        warnings.warn(f"killed {len(left)} process(es) the test left running: {left}", stacklevel=1)
