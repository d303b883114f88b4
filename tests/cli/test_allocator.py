"""glibc told to keep freed memory (`cli/allocator.py`): done on glibc, left alone where the
user set the allocator's thresholds or asked for its defaults."""

from __future__ import annotations

import platform

import pytest

from dqnlab.cli.allocator import keep_freed_memory


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="glibc's mallopt")
def test_the_thresholds_are_raised_on_glibc(monkeypatch: pytest.MonkeyPatch) -> None:
    for name in ("DQNLAB_MALLOC", "MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_"):
        monkeypatch.delenv(name, raising=False)
    assert keep_freed_memory() is True


@pytest.mark.parametrize(
    ("name", "value"),
    [("DQNLAB_MALLOC", "default"), ("MALLOC_MMAP_THRESHOLD_", "131072"),
     ("MALLOC_TRIM_THRESHOLD_", "131072")],
)  # fmt: skip
def test_the_users_own_allocator_settings_win(
    monkeypatch: pytest.MonkeyPatch, name: str, value: str
) -> None:
    monkeypatch.setenv(name, value)
    assert keep_freed_memory() is False
