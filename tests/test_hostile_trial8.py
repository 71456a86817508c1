"""The eighth hostile-input trial (issue 22; about 480 runs, docs/bad-input.md): the broken cases it found, through
the path the user took. B2 a drift direction of 1e300 overflowing the norm into no drift; B3 ``--resume`` with a
selection holding frames before the last stored one; B4 Ctrl-C while the embedded Ray starts; B5 ``batch
--ray-address`` where nothing listens."""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from cli_run import one_error, run_cli

from driftmap.fleet.reaper import _alive, adopt_orphans, descendants, is_subreaper
from driftmap.pipeline.build import build
from driftmap.sources.synthetic import SyntheticLogConfig, generate_synthetic_log
from driftmap.store.frame_store import FrameStore
from driftmap.trajectory import read_trajectory


@pytest.fixture(scope="module")
def log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return generate_synthetic_log(tmp_path_factory.mktemp("trial8") / "log", SyntheticLogConfig(n_frames=12, seed=3))


def test_t8_b2_a_huge_drift_direction_or_axis_is_a_direction(log: Path, tmp_path: Path) -> None:
    """--drift-direction 1e300,0,0 overflowed the norm (inf), the direction became 0 and the 'perturbed' file equalled
    its input (exit 0). A direction is scaled by its largest component first: the same drift as 1,0,0."""
    gt = log / "groundtruth.txt"
    for flag, huge, unit, drift in (("--drift-direction", "1e300,0,0", "1,0,0", "--drift-percent-per-m"),
                                    ("--drift-axis", "0,0,1e300", "0,0,1", "--drift-deg-per-m")):
        outputs = []
        for k, vector in enumerate((huge, unit)):
            out = tmp_path / f"{flag[2:]}-{k}.tum"
            done = run_cli("perturb", gt, out, drift, "5", flag, vector)
            assert done.returncode == 0, done.stderr[-2000:]
            assert "RuntimeWarning" not in done.stderr
            outputs.append(read_trajectory(out, "tum").poses)
        assert np.allclose(outputs[0], outputs[1], atol=1e-9)
        assert np.abs(outputs[0][:, :3, 3] - read_trajectory(gt, "tum").poses[:, :3, 3]).max() > 1e-3 \
            or not np.allclose(outputs[0][:, :3, :3], read_trajectory(gt, "tum").poses[:, :3, :3])


def test_t8_b3_resume_refuses_frames_before_the_last_stored_one(log: Path, tmp_path: Path) -> None:
    """Built with --frames 0:12:2, then resumed with every frame: the odd frames were appended after frame 10 and
    tracked backwards from it (steps of metres, exit 0). With the odometry placing the frames the resume is refused
    naming the frame and the last stored one, the store unchanged; a selection after the stored frames resumes."""
    store = tmp_path / "s"
    build(log, store, frames="0:8:2", loop_closure=False)
    with FrameStore.open(store) as s:
        before = s.poses(0).copy()
    line = one_error(run_cli("build", log, "--out", store, "--no-loop-closure", "--resume"))
    assert "would add frame 1 after frame 6" in line and "another --out" in line, line
    with FrameStore.open(store) as s:
        assert s.frame_ids.tolist() == [0, 2, 4, 6] and np.array_equal(s.poses(0), before)
    done = run_cli("build", log, "--out", store, "--no-loop-closure", "--resume", "--frames", "8:12")
    assert done.returncode == 0, done.stderr[-2000:]
    with FrameStore.open(store) as s:
        assert s.frame_ids.tolist() == [0, 2, 4, 6, 8, 9, 10, 11]


def test_t8_b5_a_ray_address_where_nothing_listens_is_refused(log: Path, tmp_path: Path) -> None:
    """batch --ray-address HOST:PORT with nothing listening waited for ever after Ray's GCS time-out. The port is
    tried first (5 s): one error line naming the address, nothing written."""
    with socket.socket() as s:  # a port nobody listens on: bound, then closed
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    line = one_error(run_cli("batch", log, "--out", tmp_path / "fleet", "--ray-address", f"127.0.0.1:{port}",
                             timeout=120))
    assert f"--ray-address 127.0.0.1:{port}: nothing answers" in line, line
    assert not (tmp_path / "fleet" / "fleet.json").exists()


def test_t8_b1_a_sphere_or_sweep_inside_unknown_space_is_never_free(room10: dict[str, Path], tmp_path: Path) -> None:
    """Unknown space was counted by voxel centres only: a point at the corner of eight unknown voxels is 0.87 voxel
    from every centre, so a sphere under 7 mm or a 5 mm box swept through it was `free` while `explore` of the same
    place said every voxel is unknown. Now the voxels' cubes count (the one holding the point always): `unknown`,
    and the clearance, sweep and explore answers agree."""
    import json

    p = [-0.46, -0.82, 1.08]  # the trial's place: a corner of the default 2 cm grid, in space no frame saw
    queries = [{"id": "r0", "kind": "clearance", "points_m": [p], "radius_m": 0.0},
               {"id": "r5mm", "kind": "clearance", "points_m": [p], "radius_m": 0.005},
               {"id": "sweep", "kind": "collision", "path_m": [[p[0] - 0.001, p[1], p[2]], [p[0] + 0.001, p[1], p[2]]],
                "footprint": {"box_m": [0.005, 0.005, 0.005]}},
               {"id": "cyl", "kind": "collision", "path_m": [[p[0] - 0.001, p[1], p[2]], [p[0] + 0.001, p[1], p[2]]],
                "footprint": {"cylinder_m": [0.003, 0.005]}},
               {"id": "region", "kind": "explore", "min_m": [p[0] - 0.02, p[1] - 0.02, p[2] - 0.02],
                "max_m": [p[0] + 0.02, p[1] + 0.02, p[2] + 0.02], "max_unknown_fraction": 0.3}]
    (tmp_path / "q.json").write_text(json.dumps({"queries": queries}))
    out = run_cli("decide", room10["gt"], "--queries", tmp_path / "q.json", "--json", tmp_path / "d.json")
    assert out.returncode == 0, out.stderr[-2000:]
    d = {x["id"]: x for x in json.loads((tmp_path / "d.json").read_text())["decisions"]}
    assert d["region"]["details"]["unknown_fraction"] == 1.0, d["region"]  # the place is unknown space
    for qid in ("r0", "r5mm", "sweep", "cyl"):
        assert d[qid]["decision"] == "unknown" and d[qid]["failure_label"] == "unknown_space", d[qid]


def test_t8_w3_w4_w7_an_empty_yaml_file_a_yaml_exponent_string_and_a_bound_are_named(log: Path, tmp_path: Path) -> None:
    """W4 an empty YAML query file ("'queries' must be a list, got NoneType"); W3 `radius_m: 1e-1`, which PyYAML
    reads as a string, refused without saying why; W7 `--drift-percent-per-m 100.0001` refused as "got 100"."""
    pytest.importorskip("yaml")
    from driftmap.decisions.errors import QueryError
    from driftmap.decisions.query_file import load_queries

    (tmp_path / "empty.yaml").write_text("# nothing yet\n")
    with pytest.raises(QueryError, match="the query file is empty"):
        load_queries(tmp_path / "empty.yaml")
    (tmp_path / "e.yaml").write_text("queries:\n  - id: c\n    kind: clearance\n    points_m: [[0, 0, 1]]\n"
                                     "    radius_m: 1e-1\n")
    with pytest.raises(QueryError, match=r"radius_m must be a number, got '1e-1' \(a number written as text.*0\.1"):
        load_queries(tmp_path / "e.yaml")
    out = run_cli("perturb", log / "groundtruth.txt", tmp_path / "p.tum", "--drift-percent-per-m", "100.0001")
    assert out.returncode == 2 and "got 100.0001" in " ".join(out.stderr.split())


def _ray_processes() -> set[int]:
    """The pids of the Ray processes running on this machine (GCS, raylet, its agents and workers)."""
    found = set()
    for entry in os.listdir("/proc"):
        try:
            with open(f"/proc/{entry}/cmdline", "rb") as f:
                cmdline = f.read().replace(b"\0", b" ")
        except OSError:
            continue
        if cmdline.startswith(b"ray::") or b"/ray/core/src/ray/" in cmdline or b"/ray/_private/" in cmdline \
                or b"/ray/dashboard/" in cmdline or b"/ray/autoscaler/" in cmdline:
            found.add(int(entry))
    return found


@pytest.mark.slow
def test_t8_b4_ctrl_c_while_the_embedded_ray_starts_leaves_no_process(log: Path, tmp_path: Path) -> None:
    """SIGINT at several moments of a batch's start (importing Ray, ray.init starting the GCS, the raylet and its
    agents, the first task): exit 130, no Ray process left running (the DashboardAgent and RuntimeEnvAgent were
    re-parented to PID 1 and ran for good), no fleet.json named unless written, no .fleet-tmp left behind."""
    pytest.importorskip("ray")
    before = _ray_processes()
    for k, delay in enumerate((2.5, 4.0, 5.5, 7.0, 9.0)):
        out = tmp_path / f"b{k}"
        proc = subprocess.Popen([sys.executable, "-m", "driftmap.cli", "batch", str(log), "--out", str(out),
                                 "--workers", "1"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        time.sleep(delay)
        proc.send_signal(signal.SIGINT)
        output, _ = proc.communicate(timeout=180)
        if proc.returncode == 0:  # the batch finished first: nothing to check at this delay
            continue
        assert proc.returncode in (130, -signal.SIGINT), (delay, proc.returncode, output[-2000:])
        assert "Traceback" not in output, (delay, output[-2000:])
        left = _ray_processes() - before
        for _ in range(50):  # what Ray stops itself may take a moment
            if not left:
                break
            time.sleep(0.1)
            left = _ray_processes() - before
        assert not left, (delay, left, output[-2000:])
        if "fleet.json" in output:
            assert (out / "fleet.json").is_file(), (delay, output[-2000:])
        assert not (out / ".fleet-tmp").exists(), delay
        if not (out / "fleet.json").exists():  # nothing ran: a rerun needs no --resume
            assert not out.exists() or "--resume" in output, (delay, output[-2000:])


def test_descendants_follow_the_whole_tree_and_prune() -> None:
    """The reaper's process walk: a grandchild is found through its parent; a pruned child hides its subtree; the
    subreaper flag is set and cleared (a batch leaves a library caller's process as it found it)."""
    if not is_subreaper():
        assert adopt_orphans() and is_subreaper()
        assert adopt_orphans(False) and not is_subreaper()
    child = subprocess.Popen(["sh", "-c", "sleep 30 & wait"])
    try:
        for _ in range(50):
            found = descendants()
            if len(found) >= 2:
                break
            time.sleep(0.05)
        assert child.pid in found and len(set(found) - {child.pid}) >= 1, found
        assert child.pid not in descendants(prune={child.pid})
        assert not set(descendants(prune={child.pid})) & set(descendants(child.pid))
    finally:
        for pid in descendants(child.pid):
            os.kill(pid, signal.SIGKILL)
        child.kill()
        child.wait()


def test_t9_a_ray_address_where_something_else_answers_is_refused(log: Path, tmp_path: Path) -> None:
    """Hostile trial 9: a port that accepts connections but is not Ray (a web server, the dashboard) got past the
    port probe and the batch waited for ever. The probe now asks for Ray's protocol (gRPC: an HTTP/2 SETTINGS frame
    in answer to the preface): one error line, nothing written."""
    import http.server
    import threading

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), http.server.SimpleHTTPRequestHandler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        port = server.server_address[1]
        line = one_error(run_cli("batch", log, "--out", tmp_path / "fleet", "--ray-address", f"127.0.0.1:{port}",
                                 timeout=120))
    finally:
        server.shutdown()
    assert f"--ray-address 127.0.0.1:{port}: something answers at 127.0.0.1:{port}, but not Ray" in line, line
    assert not (tmp_path / "fleet").exists()


_DRIVER = """
import subprocess, sys, time
from driftmap.fleet.reaper import start_watchdog
kept = subprocess.Popen(["sleep", "60"])
tree = subprocess.Popen(["sh", "-c", "sleep 60 & sleep 60 & wait"])
dog = start_watchdog(keep=[kept.pid])
time.sleep(1.5)  # the watchdog lists the tree
print(dog.pid, kept.pid, tree.pid, flush=True)
time.sleep(60)
"""


def test_t17_w11_the_watchdog_stops_what_a_killed_process_left_running() -> None:
    """W11: a `batch` driver killed outright (SIGKILL) left its embedded Ray running for good. The watchdog it starts
    stops the driver's descendants (and theirs) once the driver is gone, except those it was told to keep."""
    driver = subprocess.Popen([sys.executable, "-c", _DRIVER], stdout=subprocess.PIPE, text=True)
    dog, kept, tree = (int(x) for x in driver.stdout.readline().split())
    grandchildren = descendants(tree)
    assert len(grandchildren) == 2 and all(_alive(p) for p in (dog, kept, tree, *grandchildren))
    driver.kill()
    driver.wait()
    for _ in range(100):
        if not any(_alive(p) for p in (tree, *grandchildren)):
            break
        time.sleep(0.1)
    try:
        assert not any(_alive(p) for p in (tree, *grandchildren)), [p for p in (tree, *grandchildren) if _alive(p)]
        assert _alive(kept)  # not the watchdog's to stop
    finally:
        for pid in (kept, tree, *grandchildren, dog):
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)


def _cmdline(pid: int) -> bytes:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            return f.read()
    except OSError:
        return b""


def test_t17_w11_a_batch_killed_outright_leaves_no_ray_process(log: Path, tmp_path: Path) -> None:
    """W11 through the CLI: SIGKILL of a `driftmap batch` once its embedded Ray runs with its agents (the
    DashboardAgent and RuntimeEnvAgent ran on for good); within seconds no process it started is left."""
    pytest.importorskip("ray")
    proc = subprocess.Popen([sys.executable, "-m", "driftmap.cli", "batch", str(log), "--out", str(tmp_path / "b"),
                             "--workers", "1"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    seen: set[int] = set()
    for _ in range(600):  # until Ray's agents run
        seen |= set(descendants(proc.pid))
        if sum(_cmdline(p).startswith(b"ray::") and b"Agent" in _cmdline(p) for p in seen) >= 2 or proc.poll() is not None:
            break
        time.sleep(0.1)
    assert proc.poll() is None, "the batch finished before its Ray agents were seen"
    seen |= set(descendants(proc.pid))
    proc.kill()
    proc.wait()
    for _ in range(100):
        if not [p for p in seen if _alive(p)]:
            break
        time.sleep(0.1)
    left = {p: _cmdline(p)[:60] for p in seen if _alive(p)}
    for pid in left:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)
    assert not left, left
