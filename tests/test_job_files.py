"""A job folder's files against what happens to files: a write cut short (a full disk, a kill) leaves no
truncated file under its final name."""

from __future__ import annotations

import subprocess
import sys
import textwrap


def test_a_write_cut_short_by_a_full_disk_leaves_no_truncated_file(tmp_path):
    # a file size limit makes every write past 4 KiB fail (EFBIG), as a full disk fails it (ENOSPC)
    script = textwrap.dedent(f"""
        import resource, signal
        import numpy as np
        from pathlib import Path
        from drivers.depth.base import DepthFrame
        from cell.jobs.recorder import JobRecorder
        recorder = JobRecorder(Path({str(tmp_path / "job")!r}))
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (4096, 4096))
        points = np.random.default_rng(0).random((2000, 3))
        for attempt in (lambda: recorder.frame(DepthFrame(seq=0, timestamp=0.1, points=points), np.eye(4),
                                               np.eye(4), {{}}),
                        lambda: recorder.result({{"status": "completed", "points": points.tolist()}})):
            try:
                attempt()
            except OSError as exc:
                print(exc.errno)
    """)
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    assert res.stdout.split() == ["27", "27"]  # both writes failed: EFBIG
    job = tmp_path / "job"
    assert not (job / "frames" / "000000.npz").exists()
    assert not (job / "result.json").exists()
    assert sorted(p.name for p in job.rglob(".*")) == []  # no temporary file left either
