"""``driftmap batch`` on Ray (issue 27, docs/fleet.md): a batch of synthetic logs gives each log exactly what a
sequential ``build --threads 1`` + ``diagnose`` gives; a corrupt log fails alone with its typed error; a worker killed
mid-task is retried; Ctrl-C leaves only complete logs and ``--resume`` redoes only the unfinished ones; the command
line writes ``fleet.json`` per the contract and refuses bad input with one error line.

One Ray (2 CPUs) serves the library batches of this module; the command-line test starts its own embedded Ray."""

from __future__ import annotations

import functools
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import ray

from driftmap import errors
from driftmap.config import DriftmapConfig
from driftmap.fleet import (
    CONTRACT_KEYS,
    FleetProgress,
    LogSpec,
    expand_inputs,
    load_batch_config,
    run_batch,
    synth_fleet,
)
from driftmap.fleet.config import CONFIG_FILE, config_hash
from driftmap.fleet.folders import BATCH_LOCK, RESULT_FILE, TMP_DIR, completed_result
from driftmap.fleet.report import rank_worst_first
from driftmap.pipeline.build import BuildConfig, build
from driftmap.pipeline.diagnose import run_diagnose
from driftmap.store.frame_store import FrameStore

ROOMS = ("room-00", "room-01", "room-02", "room-03")
BROKEN = "broken-00-truncated-depth"
CONFIG = """\
[build.loop_closure]
max_candidates_per_keyframe = 4

[diagnose.sampling]
points_per_frame = 1500

[fleet]
exports = ["trajectory"]
"""


def _cli(*args: object, timeout: float = 300) -> subprocess.CompletedProcess:
    env = {**os.environ, "COLUMNS": "200"}
    return subprocess.run([sys.executable, "-m", "driftmap.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout, env=env)


def _one_line_error(out: subprocess.CompletedProcess) -> str:
    assert out.returncode == 1, (out.returncode, out.stdout, out.stderr)
    assert "Traceback" not in out.stderr, out.stderr
    lines = [line for line in out.stderr.strip().splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:"), out.stderr
    return lines[0]


def kill_worker_once(spec: LogSpec, stage: str, *, victim: str, marker: str) -> None:
    """The test's hook: the first time ``victim`` is built, its worker process SIGKILLs itself (the store is written,
    its temporary folder left behind); the marker records the killed process."""
    if spec.name == victim and stage == "built" and not os.path.exists(marker):
        Path(marker).write_text(str(os.getpid()))
        os.kill(os.getpid(), signal.SIGKILL)


@pytest.fixture(scope="module")
def shared_ray():
    """One Ray for the library batches of this module (run_batch uses a Ray that is running and leaves it)."""
    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])  # the hook above, for the workers
    ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False, logging_level="ERROR")
    yield
    ray.shutdown()


@pytest.fixture(scope="module")
def fleet_logs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("fleet") / "logs"
    synth_fleet(out, len(ROOMS), broken=1)
    assert sorted(p.name for p in out.iterdir()) == sorted([*ROOMS, BROKEN])
    return out


@pytest.fixture(scope="module")
def config_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("config") / "batch.toml"
    path.write_text(CONFIG)
    return path


@pytest.fixture(scope="module")
def batch(shared_ray, fleet_logs: Path, config_file: Path, tmp_path_factory: pytest.TempPathFactory):
    """The five logs (four rooms, one broken) with 2 workers; room-01's worker is killed after its build."""
    root = tmp_path_factory.mktemp("batch")
    marker = root / "killed"
    hook = functools.partial(kill_worker_once, victim="room-01", marker=str(marker))
    result = run_batch(expand_inputs([str(fleet_logs / "*")]), root / "out", load_batch_config(config_file),
                       workers=2, hook=hook)
    return result, marker


@pytest.fixture(scope="module")
def reference(batch, fleet_logs: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Each room log built with one thread and diagnosed, one after the other, in this process: what ``driftmap build
    --threads 1 --config C`` + ``driftmap diagnose --config C --gt LOG/groundtruth.txt`` (with ``--compare-revision
    0`` after a loop closure) write, C being the batch's fleet_config.json."""
    cfg = batch[0].out_dir / CONFIG_FILE
    root = tmp_path_factory.mktemp("reference")
    for name in ROOMS:
        log = fleet_logs / name
        built = build(log, root / name / "store", config=BuildConfig.load(cfg).model_copy(update={"num_threads": 1}),
                      depth=DriftmapConfig.load(cfg).depth)
        with FrameStore.open(root / name / "store") as store:
            run_diagnose(store, root / name / "diagnosis.json", gt=log / "groundtruth.txt", gt_format="tum",
                         compare_revision=0 if built.loop_revision is not None else None, config_file=cfg)
    return root


def _diagnosis(path: Path) -> str:
    data = json.loads(path.read_text())
    data.pop("seconds")  # wall times
    data.pop("store_uuid")  # each store's own id (the batch's and the reference's are two stores)
    return json.dumps(data, sort_keys=True)


def test_batch_gives_each_log_what_a_sequential_build_and_diagnose_give(batch, reference: Path) -> None:
    result, _ = batch
    rows = {r["name"]: r for r in result.rows}
    assert result.workers == 2 and result.threads == 1
    for name in ROOMS:
        assert rows[name]["status"] == "ok", rows[name]
        with FrameStore.open(result.out_dir / name / "store") as got, FrameStore.open(reference / name / "store") as want:
            assert [r.revision_id for r in got.revisions] == [r.revision_id for r in want.revisions]
            for rev in want.revisions:
                assert got.poses(rev.revision_id).tobytes() == want.poses(rev.revision_id).tobytes(), (name, rev)
            assert np.array_equal(got.frame_ids, want.frame_ids)
        assert _diagnosis(result.out_dir / name / "diagnosis.json") == _diagnosis(reference / name / "diagnosis.json")
        assert (result.out_dir / name / "trajectory.tum").is_file()
        assert rows[name]["frames"] == 40 and rows[name]["ate_rmse_m"] is not None
    assert any(rows[n]["loop_revision"] is not None for n in ROOMS)  # a loop closure among them (before / after)


def test_a_corrupt_log_fails_alone_with_its_typed_error(batch) -> None:
    result, _ = batch
    data = json.loads((result.out_dir / "fleet.json").read_text())
    rows = {r["name"]: r for r in data["logs"]}
    failed = rows[BROKEN]
    assert failed["status"] == "failed" and "/depth/" in failed["error"] and ".png" in failed["error"], failed
    assert issubclass(getattr(errors, failed["error_type"]), errors.DriftmapError), failed["error_type"]
    assert not (result.out_dir / BROKEN).exists()
    assert [rows[n]["status"] for n in ROOMS] == ["ok"] * len(ROOMS)
    assert data["counts"] == {"ok": 4, "failed": 1, "skipped": 0}


def test_a_killed_worker_is_retried_and_leaves_nothing_partial(batch) -> None:
    result, marker = batch
    assert marker.is_file(), "the hook did not kill room-01's worker"
    record = json.loads((result.out_dir / "room-01" / RESULT_FILE).read_text())
    assert record["row"]["status"] == "ok" and record["pid"] != int(marker.read_text())
    assert not (result.out_dir / TMP_DIR).exists()  # the killed attempt's store was removed, and the empty folder


def test_fleet_report_ranks_the_logs_worst_first(batch) -> None:
    result, _ = batch
    page = (result.out_dir / "fleet.html").read_text()
    ranked = [r["name"] for r in rank_worst_first(result.rows)]
    assert sorted(ranked) == list(ROOMS)
    assert [page.index(f">{n}</a>") for n in ranked] == sorted(page.index(f">{n}</a>") for n in ranked)
    assert BROKEN in page.split("<h2>Failures</h2>")[1]
    for png in ("fleet_ranking.png", "fleet_drift.png"):
        assert (result.out_dir / png).read_bytes()[:4] == b"\x89PNG"


def test_ctrl_c_leaves_complete_logs_and_resume_redoes_only_the_unfinished(shared_ray, batch, fleet_logs: Path,
                                                                           config_file: Path, tmp_path: Path) -> None:
    listing = tmp_path / "logs.txt"  # a list file, relative paths, one with its own name
    listing.write_text("# three rooms\n" + "".join(f"{fleet_logs / n}\n" for n in ROOMS[:2])
                       + f"{os.path.relpath(fleet_logs / ROOMS[2], tmp_path)} --name third\n")
    specs = expand_inputs([str(listing)])
    assert [s.name for s in specs] == ["room-00", "room-01", "third"]
    config, out = load_batch_config(config_file), tmp_path / "out"

    def interrupt(state: FleetProgress) -> None:  # Ctrl-C as soon as the first log is done
        if state.done >= 1:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_batch(specs, out, config, workers=2, progress=interrupt)
    data = json.loads((out / "fleet.json").read_text())
    finished = {r["name"] for r in data["logs"]}
    assert finished and set(data["interrupted"]) == {"room-00", "room-01", "third"} - finished
    present = {p.name for p in out.iterdir() if p.is_dir() and not p.name.startswith(".")}
    assert present == finished  # only complete logs, nothing half-written
    assert all(completed_result(out / n, config_hash(config, s)) for s in specs for n in [s.name] if n in finished)
    assert not (out / TMP_DIR).exists()
    stamps = {n: (out / n / RESULT_FILE).stat().st_mtime_ns for n in finished}

    with pytest.raises(errors.ConfigError, match="--resume"):
        run_batch(specs, out, config, workers=2)
    resumed = run_batch(specs, out, config, workers=2, resume=True)
    status = {r["name"]: r["status"] for r in resumed.rows}
    assert status == {n: "skipped" if n in finished else "ok" for n in ("room-00", "room-01", "third")}
    assert stamps == {n: (out / n / RESULT_FILE).stat().st_mtime_ns for n in finished}  # kept as they were
    # the resumed third log is the batch's room-02, to the bit
    with FrameStore.open(out / "third" / "store") as a, FrameStore.open(batch[0].out_dir / "room-02" / "store") as b:
        assert a.poses().tobytes() == b.poses().tobytes()


def test_resume_redoes_a_log_made_with_another_config(batch, fleet_logs: Path, tmp_path: Path) -> None:
    spec = expand_inputs([str(fleet_logs / "room-00")])[0]
    folder = batch[0].out_dir / "room-00"
    same = load_batch_config(None)
    other_file = tmp_path / "other.json"
    other_file.write_text(json.dumps({"diagnose": {"sampling": {"points_per_frame": 1500}},
                                      "build": {"loop_closure": {"max_candidates_per_keyframe": 4}},
                                      "fleet": {"exports": ["trajectory", "map"]}}))
    assert completed_result(folder, json.loads((folder / RESULT_FILE).read_text())["config_hash"])
    assert config_hash(load_batch_config(other_file), spec) != config_hash(same, spec)
    assert completed_result(folder, config_hash(same, spec)) is None


def test_list_file_mistakes_name_the_line(tmp_path: Path, fleet_logs: Path) -> None:
    listing = tmp_path / "logs.list"
    listing.write_text(f"{fleet_logs / 'room-00'}\n\n{fleet_logs / 'room-01'} --senser lidar\n")
    with pytest.raises(errors.ConfigError, match=rf"{listing}:3: unknown option '--senser'"):
        expand_inputs([str(listing)])
    listing.write_text(f"{fleet_logs / 'room-00'} --poses\n")
    with pytest.raises(errors.ConfigError, match=rf"{listing}:1: --poses needs a value"):
        expand_inputs([str(listing)])
    listing.write_text("no-such-log --sensor depth\n")
    with pytest.raises(errors.ConfigError, match=rf"{listing}:1: no-such-log: no such log"):
        expand_inputs([str(listing)])
    # trial 17 W6: --gt-format without --gt was ignored; diagnose refuses it, and so does a list line (CLI path)
    listing.write_text(f"{fleet_logs / 'room-00'}\n{fleet_logs / 'room-01'} --gt-format euroc\n")
    line = _one_line_error(_cli("batch", listing, "--out", tmp_path / "out"))
    assert f"{listing}:2: --gt-format describes the --gt FILE; give one" in line, line
    assert not (tmp_path / "out").exists()


def test_cli_synth_fleet_then_batch_writes_the_contract(tmp_path: Path, config_file: Path) -> None:
    logs, out = tmp_path / "logs", tmp_path / "out"
    made = _cli("synth", "--fleet", 2, "--broken", 1, logs)
    assert made.returncode == 0, made.stderr
    inputs = sorted(str(p) for p in logs.iterdir())  # as the shell expands logs/*
    assert [Path(p).name for p in inputs] == [BROKEN, "room-00", "room-01"]
    ran = _cli("batch", *inputs, "--out", out, "--workers", 2, "--config", config_file, timeout=600)
    assert ran.returncode == 1 and "Traceback" not in ran.stderr, ran.stderr  # a batch with a failed log: exit 1
    assert ran.stderr.strip().splitlines()[-1] == f"error: 1 of 3 logs failed; their errors are in {out / 'fleet.json'}"
    assert f"failed: {BROKEN}: " in ran.stderr and "room-01" in ran.stdout  # as it happened, then the summary
    data = json.loads((out / "fleet.json").read_text())
    assert {"logs", "workers", "ray_address"} <= set(data) and data["workers"] == 2 and data["ray_address"] is None
    types = {"name": str, "input": str, "status": str, "frames": int, "time_s": float}
    for row in data["logs"]:
        assert set(CONTRACT_KEYS) <= set(row), row
        assert all(isinstance(row[k], t) for k, t in types.items()), row
        assert row["status"] in ("ok", "failed", "skipped")
        numbers = ("ate_rmse_m", "drift_percent_per_m", "fraction_flagged", "smearing_score_m")
        assert all(row[k] is None or isinstance(row[k], float) for k in numbers), row
        assert (row["error"] is None) == (row["status"] == "ok")
        if row["status"] == "ok":
            assert {"store", "diagnosis.json", "trajectory.tum"} <= {p.name for p in (out / row["name"]).iterdir()}
    assert [r["status"] for r in data["logs"]] == ["failed", "ok", "ok"]


@pytest.mark.parametrize(("args", "expected"), [
    (["{tmp}/nothing-here-*"], "matched no log"),
    (["{tmp}/missing.txt"], "missing.txt: no such list file"),
])
def test_cli_bad_inputs_are_one_error_line(tmp_path: Path, args: list[str], expected: str) -> None:
    out = _cli("batch", *[a.format(tmp=tmp_path) for a in args], "--out", tmp_path / "out")
    assert expected in _one_line_error(out)
    assert not (tmp_path / "out").exists()


def test_cli_without_ray_says_how_to_install_it(tmp_path: Path) -> None:
    code = ("import sys; sys.modules['ray'] = None; sys.argv = ['driftmap', 'batch', 'x', '--out', 'y']; "
            "from driftmap.cli import main; main()")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert "pip install 'driftmap[fleet]'" in _one_line_error(out)


def test_synth_fleet_refuses_options_it_does_not_take(tmp_path: Path) -> None:
    out = _cli("synth", "--fleet", 2, "--scene", "street", tmp_path / "f")
    assert out.returncode == 2 and "--scene" in out.stderr
    assert not (tmp_path / "f").exists()


def test_cli_resume_redoes_a_log_whose_store_is_damaged(batch, fleet_logs: Path, config_file: Path,
                                                         tmp_path: Path) -> None:
    """B6: a log folder whose result.json says ok but whose store lost a segment is not `skipped` on --resume: it
    is run again and its folder replaced; an intact one is kept."""
    import shutil

    out = tmp_path / "out"
    shutil.copytree(batch[0].out_dir, out)
    (out / "room-00" / "store" / "segment-000000.mcap").unlink()
    config = load_batch_config(config_file)
    specs = {s.name: s for s in expand_inputs([str(fleet_logs / "room-00"), str(fleet_logs / "room-01")])}
    assert completed_result(out / "room-00", config_hash(config, specs["room-00"])) is None
    assert completed_result(out / "room-01", config_hash(config, specs["room-01"])) is not None
    kept = (out / "room-01" / RESULT_FILE).stat().st_mtime_ns
    ran = _cli("batch", fleet_logs / "room-00", fleet_logs / "room-01", "--out", out, "--resume", "--workers", 1,
               "--config", config_file, timeout=600)
    assert ran.returncode == 0, ran.stderr
    status = {r["name"]: (r["status"], r["frames"]) for r in json.loads((out / "fleet.json").read_text())["logs"]}
    assert status == {"room-00": ("ok", 40), "room-01": ("skipped", 40)}
    with FrameStore.open(out / "room-00" / "store") as store:
        assert len(store) == 40
    assert (out / "room-01" / RESULT_FILE).stat().st_mtime_ns == kept
    assert not (out / TMP_DIR).exists()


def test_cli_refuses_an_out_among_the_inputs_and_reserved_names(fleet_logs: Path, tmp_path: Path) -> None:
    """W7, W8, W9: a reserved --name says it is reserved; --out equal to an input, or inside one, is refused."""
    log = fleet_logs / "room-00"
    before = sorted(p.relative_to(log) for p in log.rglob("*"))
    listing = tmp_path / "logs.txt"
    for name in ("fleet.json", ".fleet-tmp"):
        listing.write_text(f"{log} --name {name}\n")
        line = _one_line_error(_cli("batch", listing, "--out", tmp_path / "out"))
        assert f"{listing}:1: --name: '{name}' is reserved" in line and "not a usable" not in line, line
    line = _one_line_error(_cli("batch", log, "--out", log))
    assert f"--out {log}: is one of the inputs" in line and "no log among" not in line, line
    line = _one_line_error(_cli("batch", log, "--out", log / "depth" / "fl"))
    assert f"--out {log / 'depth' / 'fl'}: is inside the input {log}" in line, line
    assert not (tmp_path / "out").exists()
    assert sorted(p.relative_to(log) for p in log.rglob("*")) == before  # nothing written into the log


def test_failed_log_errors_name_the_final_folder_and_how_to_drop_ground_truth(fleet_logs: Path, config_file: Path,
                                                                               tmp_path: Path,
                                                                               monkeypatch: pytest.MonkeyPatch) -> None:
    """W10: a log too short for ATE/RPE with ground_truth "auto" says how to turn it off; trial 24 W7: that
    optional ground truth no longer fails the log -- it is diagnosed without it (no ATE) and the row says why. An
    export failure names DIR/<name>/mesh.ply, not the temporary folder that is gone by then."""
    from driftmap.errors import EmptyExportError
    from driftmap.fleet.report import write_fleet_report
    from driftmap.fleet.task import run_log

    out = tmp_path / "out"
    spec = LogSpec(name="one", input=str(fleet_logs / "room-00"), frames="0:2")
    row = run_log(spec, load_batch_config(config_file), out)
    assert row["status"] == "ok" and row["error"] is None and row["ate_rmse_m"] is None, row
    note = row["ground_truth_error"]
    assert "ATE/RPE need at least 3" in note and '[fleet] ground_truth = "none"' in note, note
    assert TMP_DIR not in note and "diagnosed without it" in note, note
    assert "ATE/RPE need at least 3" in (out / "one" / "log.txt").read_text()
    write_fleet_report(out, [row])
    assert "Ground truth left out" in (out / "fleet.html").read_text()
    # a ground truth the list gives (--gt) is the user's: its failure still fails the log
    spec = LogSpec(name="two", input=str(fleet_logs / "room-00"), frames="0:2",
                   gt=str(fleet_logs / "room-00" / "groundtruth.txt"), gt_format="tum")
    row = run_log(spec, load_batch_config(config_file), out)
    assert row["status"] == "failed" and "ATE/RPE need at least 3" in row["error"], row

    def no_surface(layers, path, *, flag="--mesh", **_):
        raise EmptyExportError(f"{flag} {path}: the TSDF has no surface to mesh")

    monkeypatch.setattr("driftmap.volume.export.write_mesh", no_surface)
    mesh_config = tmp_path / "mesh.toml"
    mesh_config.write_text(CONFIG.replace('exports = ["trajectory"]', 'exports = ["mesh"]\nground_truth = "none"'))
    spec = LogSpec(name="meshed", input=str(fleet_logs / "room-00"), frames="0:4")
    row = run_log(spec, load_batch_config(mesh_config), out)
    assert row["status"] == "failed" and f"{out / 'meshed' / 'mesh.ply'}:" in row["error"], row["error"]
    assert TMP_DIR not in row["error"] and "--mesh" not in row["error"], row["error"]
    assert not (out / "meshed").exists()


def test_cli_a_ray_that_cannot_start_is_one_error_line(fleet_logs: Path, tmp_path: Path) -> None:
    """W11: ray.init failing (as on a loaded machine) is one error line saying Ray could not start and why."""
    out = tmp_path / "out"
    code = ("import sys, ray\n"
            "def boom(*a, **k):\n"
            "    raise Exception('The current node timed out during startup. This could happen because some of the "
            "Ray processes failed to startup.')\n"
            "ray.init = boom\n"
            f"sys.argv = ['driftmap', 'batch', {str(fleet_logs / 'room-00')!r}, '--out', {str(out)!r}]\n"
            "from driftmap.cli import main; main()\n")
    ran = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=tmp_path,
                         check=False)
    line = _one_line_error(ran)
    assert "Ray could not start" in line and "The current node timed out during startup" in line, line
    assert not out.exists()


def test_cli_resume_redoes_a_log_replaced_in_place(config_file: Path, tmp_path: Path) -> None:
    """Trial 16 W12: `--resume` kept a log's old results after its files were replaced (same path, same options): 15
    frames recorded for a log of 12. result.json now records the input files' fingerprint; a changed one is run
    again, an unchanged one skipped."""
    logs = tmp_path / "logs"
    for name, seed in (("room-a", 1), ("room-b", 2)):
        assert _cli("synth", logs / name, "--frames", 10, "--seed", seed).returncode == 0
    out = tmp_path / "out"
    first = _cli("batch", logs / "room-a", logs / "room-b", "--out", out, "--workers", 1, "--config", config_file,
                 timeout=600)
    assert first.returncode == 0, first.stderr
    kept = (out / "room-b" / RESULT_FILE).stat().st_mtime_ns
    assert json.loads((out / "room-a" / RESULT_FILE).read_text())["input_fingerprint"]
    replaced = _cli("synth", logs / "room-a", "--frames", 8, "--seed", 3, "--overwrite")
    assert replaced.returncode == 0, replaced.stderr
    again = _cli("batch", logs / "room-a", logs / "room-b", "--out", out, "--resume", "--workers", 1, "--config",
                 config_file, timeout=600)
    assert again.returncode == 0, again.stderr
    assert "input files changed" in " ".join(again.stderr.split()), again.stderr
    status = {r["name"]: (r["status"], r["frames"]) for r in json.loads((out / "fleet.json").read_text())["logs"]}
    assert status == {"room-a": ("ok", 8), "room-b": ("skipped", 10)}
    assert (out / "room-b" / RESULT_FILE).stat().st_mtime_ns == kept


def test_cli_a_second_batch_into_a_folder_a_batch_is_writing_is_refused(batch, fleet_logs: Path, config_file: Path,
                                                                        tmp_path: Path) -> None:
    """Two batches into one --out: the second's --resume took the first's logs in progress (DIR/.fleet-tmp) for an
    interrupted batch's and removed them. The running batch holds DIR/.fleet-batch.lock; a second is refused, naming
    the process, and touches nothing; once the lock is free, --resume goes on."""
    import fcntl
    import shutil

    out = tmp_path / "out"
    shutil.copytree(batch[0].out_dir, out)
    in_progress = out / TMP_DIR / "room-00.0a1b2c3d"
    in_progress.mkdir(parents=True)
    (in_progress / "partial").write_text("a log being written")
    with open(out / BATCH_LOCK, "a+") as held:  # the running batch
        fcntl.flock(held.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        held.seek(0)
        held.truncate()
        held.write("424242\n")
        held.flush()
        line = _one_line_error(_cli("batch", fleet_logs / "room-01", "--out", out, "--resume", "--config",
                                    config_file))
        assert "another driftmap batch (process 424242) is writing into it" in line, line
        assert (in_progress / "partial").is_file()
    ran = _cli("batch", fleet_logs / "room-01", "--out", out, "--resume", "--config", config_file)
    assert ran.returncode == 0, ran.stderr
    assert not in_progress.exists()  # the lock was free: what was left is an interrupted batch's
