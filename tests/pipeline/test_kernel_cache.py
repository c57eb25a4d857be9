"""The compiled kernels' cache kept to its sources (pipeline.parallel.drop_stale_kernels)."""

from __future__ import annotations

import os

from pipeline.parallel import drop_stale_kernels as drop_stale


def _package(root):
    (root / "sub" / "__pycache__").mkdir(parents=True)
    (root / "__pycache__").mkdir()
    (root / "a.py").write_text("import numba\n")
    (root / "sub" / "b.py").write_text("import numba  # y = 2\n")
    (root / "plain.py").write_text("z = 3\n")
    return root


def _cache(root):
    files = [
        root / "__pycache__" / "a.kernel-1.py311.nbi",
        root / "sub" / "__pycache__" / "b.k-2.py311.nbc",
    ]
    for f in files:
        f.write_bytes(b"compiled")
    return files


def test_a_cache_without_a_fingerprint_is_dropped_then_kept(tmp_path):
    root = _package(tmp_path)
    stale = _cache(root)
    assert drop_stale(root) is True
    assert not any(f.exists() for f in stale)
    fresh = _cache(root)  # compiled again by the kernels' first calls
    assert drop_stale(root) is False
    assert all(f.exists() for f in fresh)


def test_a_changed_source_in_any_module_drops_every_kernel(tmp_path):
    # the caller's module (a.py) is unchanged; the callee's (sub/b.py) changed: the caller's cache holds
    # the old callee compiled in, so it goes too
    root = _package(tmp_path)
    drop_stale(root)
    cached = _cache(root)
    b = root / "sub" / "b.py"
    b.write_text("import numba  # y = 3\n")
    st = b.stat()
    os.utime(b, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000))
    assert drop_stale(root) is True
    assert not any(f.exists() for f in cached)
    assert drop_stale(root) is False


def test_a_module_without_kernels_changes_nothing(tmp_path):
    root = _package(tmp_path)
    drop_stale(root)
    cached = _cache(root)
    (root / "plain.py").write_text("z = 4  # a longer line\n")
    assert drop_stale(root) is False
    assert all(f.exists() for f in cached)


def test_a_package_that_cannot_be_written_is_left_as_it_is(tmp_path, monkeypatch):
    # an installed, read-only package (the tests run as root, which the mode bits do not stop: the
    # file system's refusal is what the code meets)
    root = _package(tmp_path)
    cached = _cache(root)

    def refused(self, missing_ok=False):
        raise PermissionError(13, "Permission denied", str(self))

    monkeypatch.setattr(type(root), "unlink", refused)
    assert drop_stale(root) is False
    assert all(f.exists() for f in cached)
    assert not (root / "__pycache__" / "kernels.stamp").exists()
