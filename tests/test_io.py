"""Writing files: whole or not at all."""

import os

from nerf_lightning.io import write_atomic


def test_atomic_writes_leave_no_temporary_file_and_the_usual_permissions(tmp_path):
    path = write_atomic(tmp_path / "out" / "metrics.json", b"{}")
    mask = os.umask(0)
    os.umask(mask)
    assert path.read_bytes() == b"{}" and (path.stat().st_mode & 0o777) == 0o666 & ~mask
    assert [p.name for p in path.parent.iterdir()] == ["metrics.json"]
