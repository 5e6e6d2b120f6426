"""``plantscan batch``: real pipeline, Dask local cluster and a real scheduler/worker pair."""

from __future__ import annotations

import csv
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
from batch_fixtures import PLUGINS, crash_on_scan_named_crash

from plantscan_core.batch import ERROR_TXT, _run_dirs, process_plant, run_batch
from plantscan_core.data import Traits
from plantscan_core.errors import DataError, RecipeError


def _csv(path: Path) -> list[dict[str, str]]:
    return list(csv.DictReader(path.open()))


def _check_two_good_one_corrupt(out: Path, scans: dict[str, Path]) -> list[dict[str, str]]:
    """The user-visible contract of a batch with one corrupt scan, read from its files."""
    rows = {Path(r["scan"]).name: r for r in _csv(out / "batch_summary.csv")}
    assert set(rows) == {"good1", "good2", "corrupt"}
    assert rows["good1"]["status"] == rows["good2"]["status"] == "ok"
    # ran, but not to be trusted: the summary says so and why (16 views, the recipe needs 36)
    for name in ("good1", "good2"):
        assert rows[name]["quality_flag"] == "fail"
        assert "16 plant views, fewer than the 36" in rows[name]["quality_reasons"]
    bad = rows["corrupt"]
    assert bad["status"] == "failed"
    # The error names the stage and the unreadable image file, so the technician can act.
    assert "segment" in bad["error"] and "cannot decode image" in bad["error"]
    assert str(scans["corrupt"] / "images" / "plant") in bad["error"]
    assert "Traceback" in (out / "corrupt" / ERROR_TXT).read_text()
    # traits_all.csv holds exactly the leaves of the two good plants, as each run measured them.
    leaves = _csv(out / "traits_all.csv")
    assert {Path(r["scan"]).name for r in leaves} == {"good1", "good2"}
    for name in ("good1", "good2"):
        run_traits = Traits.load(out / name / "traits.csv")
        mine = [r for r in leaves if Path(r["scan"]).name == name]
        assert len(mine) == len(run_traits.leaves) == int(rows[name]["leaf_count"]) > 0
        assert [float(r["area_mm2"]) for r in mine] == pytest.approx(
            [leaf.area_mm2 for leaf in run_traits.leaves], abs=1e-4)  # CSV keeps 4 decimals
        assert [r["quality_flag"] for r in mine] == [lf.quality_flag for lf in run_traits.leaves]
        assert all(0.0 <= float(r["confidence"]) <= 1.0 for r in mine)
        # run.json of the plant's run folder is the pipeline's: every stage ran.
        info = json.loads((out / name / "run.json").read_text())
        assert {"calibrate", "segment", "reconstruct", "mesh", "segment_mesh",
                "measure"} <= set(info["stages"])
        assert (out / name / "report.html").stat().st_size > 1_000_000  # plotly.js inline
    assert not (out / "corrupt" / "report.html").exists()
    # Different plants (seeds 1 and 2): the batch did not process one scan twice.
    assert rows["good1"]["total_leaf_area_mm2"] != rows["good2"]["total_leaf_area_mm2"]
    return list(rows.values())


# --------------------------------------------------------------------------- fast
def test_run_folders_are_named_after_scans_and_never_collide(tmp_path: Path):
    dirs = _run_dirs([tmp_path / "a" / "p1", tmp_path / "p1-2", tmp_path / "b" / "p1",
                      tmp_path / "p2"], tmp_path / "out")
    assert [d.name for d in dirs] == ["p1", "p1-2", "p1-3", "p2"]


def test_a_broken_recipe_fails_once_before_any_work(tmp_path: Path, batch_recipe):
    with pytest.raises(RecipeError) as err:
        run_batch([tmp_path / "some-scan"], batch_recipe, tmp_path / "out",
                  overrides=["segment.plugin=no-such-segmenter"], progress=False)
    assert "segment.plugin" in str(err.value)
    assert not (tmp_path / "out").exists()  # no cluster started, nothing written


def test_a_missing_session_calibration_fails_once_before_any_work(tmp_path: Path,
                                                                   batch_recipe):
    with pytest.raises(DataError, match="no-such-calibration.yaml"):
        run_batch([tmp_path / "some-scan"], batch_recipe, tmp_path / "out", progress=False,
                  calibration=tmp_path / "no-such-calibration.yaml")
    assert not (tmp_path / "out").exists()


def test_a_plant_task_returns_its_failure_instead_of_raising(tmp_path: Path, batch_recipe):
    recipe = batch_recipe
    not_a_scan = tmp_path / "empty-folder"
    not_a_scan.mkdir()
    outcome = process_plant(str(not_a_scan), str(recipe), [], str(tmp_path / "run"))
    assert outcome.status == "failed" and outcome.leaf_count is None
    assert f"{not_a_scan / 'scan.yaml'}: missing" in outcome.error
    assert (tmp_path / "run" / ERROR_TXT).exists()


# --------------------------------------------------------------------------- end to end
@pytest.mark.slow
def test_a_session_calibration_replaces_calibrating_each_plant(tmp_path: Path, batch_inputs):
    # The virtual scanner's exact calibration stands for the session's: every plant uses it
    # (no board detection), and the plant is measured as usual.
    scans, recipe = batch_inputs
    session = scans["good1"] / "ground_truth" / "calibration.yaml"
    outcome = process_plant(str(scans["good1"]), str(recipe), [], str(tmp_path / "run"),
                            calibration_path=str(session))
    assert outcome.status == "ok", outcome.error
    assert outcome.leaf_count and outcome.leaf_count > 0
    info = json.loads((tmp_path / "run" / "run.json").read_text())
    assert info["stages"]["calibrate"]["plugin"] == "--calibration"
    assert info["stages"]["calibrate"]["file"] == str(session)


@pytest.mark.slow
def test_cli_batch_on_a_two_worker_local_cluster(tmp_path: Path, batch_inputs, capsys):
    from plantscan_core.cli import main

    scans, recipe = batch_inputs
    out = tmp_path / "out"
    status = main(["batch", str(scans["good1"]), str(scans["corrupt"]), str(scans["good2"]),
                   "--recipe", str(recipe), "--workers", "2", "--out", str(out)])
    assert status != 0  # one plant failed
    captured = capsys.readouterr()
    printed = captured.out
    assert "2 succeeded, 1 failed" in printed and "local cluster (2 workers)" in printed
    # Progress without a terminal (pytest's stderr): the batch's step with its plant count,
    # one line per plant as it finishes, its end; no nanny's "killing" lines at the close.
    err = captured.err.splitlines()
    assert "plants on local cluster (2 workers): started (3 plants)" in err, captured.err
    assert sum(ln.startswith("ok good") for ln in err) == 2
    assert sum(ln.startswith("FAILED corrupt") for ln in err) == 1
    assert any(ln.startswith("plants on local cluster (2 workers): done in") for ln in err)
    assert "killing" not in captured.err
    rows = _check_two_good_one_corrupt(out, scans)
    # Both worker processes of the cluster took plants (3 tasks submitted at once to 2 idle
    # single-thread workers: the scheduler gives each at least one).
    assert len({r["worker"] for r in rows}) == 2


@pytest.mark.slow
def test_a_plant_that_kills_its_worker_is_reported_and_the_others_finish(tmp_path: Path,
                                                                         batch_recipe):
    import dask

    scans = [tmp_path / name for name in ("first", "crash", "last")]
    # No retries of the crashing task on fresh workers: one death is enough to report it.
    with dask.config.set({"distributed.scheduler.allowed-failures": 0}):
        summary = run_batch(scans, batch_recipe, tmp_path / "out", workers=2, progress=False,
                            task=crash_on_scan_named_crash)
    status = {Path(p.scan).name: p for p in summary.plants}
    assert status["first"].ok and status["last"].ok
    assert not status["crash"].ok
    assert "task failed on the cluster" in status["crash"].error
    assert "KilledWorker" in status["crash"].error
    assert summary.failed == 1


def _start(cmd: list[str], log: Path, env: dict[str, str]) -> subprocess.Popen:
    return subprocess.Popen(cmd, stdout=log.open("wb"), stderr=subprocess.STDOUT, env=env,
                            start_new_session=True)


def _stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)


def _read_json(path: Path) -> dict | None:
    """``path``'s JSON, or None while it is missing or not yet completely written."""
    try:
        return json.loads(path.read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        return None


@pytest.mark.slow
def test_batch_through_a_real_dask_scheduler_and_worker(tmp_path: Path, batch_inputs):
    from distributed import Client

    dask = shutil.which("dask", path=str(Path(sys.executable).parent)) or shutil.which("dask")
    if dask is None:
        pytest.skip("the `dask` command of dask.distributed is not installed")
    scans, recipe = batch_inputs
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(PLUGINS), *filter(None, [os.environ.get("PYTHONPATH")])])}
    sched_file = tmp_path / "scheduler.json"
    scheduler = _start([dask, "scheduler", "--host", "127.0.0.1", "--port", "0",
                        "--no-dashboard", "--scheduler-file", str(sched_file)],
                       tmp_path / "scheduler.log", env)
    worker = None
    try:
        deadline = time.monotonic() + 60
        # The scheduler creates its file, then writes it: wait for a whole JSON document (an
        # empty file was read once on a loaded machine, a JSONDecodeError).
        while (info := _read_json(sched_file)) is None:
            assert scheduler.poll() is None, (tmp_path / "scheduler.log").read_text()
            assert time.monotonic() < deadline, "dask scheduler did not start within 60 s"
            time.sleep(0.2)
        address = info["address"]
        assert address.startswith("tcp://127.0.0.1:")
        worker = _start([dask, "worker", address, "--nthreads", "1", "--nworkers", "1",
                         "--host", "127.0.0.1", "--no-dashboard", "--name", "plantscan-test"],
                        tmp_path / "worker.log", env)
        with Client(address, timeout=30) as client:
            client.wait_for_workers(1, timeout=90)
            worker_addresses = set(client.scheduler_info()["workers"])
        out = tmp_path / "out"
        summary = run_batch([scans["good1"], scans["good2"], scans["corrupt"]], recipe, out,
                            scheduler=address, progress=False)
        assert summary.failed == 1 and summary.succeeded == 2 and summary.exit_status == 1
        assert summary.scheduler == f"scheduler {address}"
        rows = _check_two_good_one_corrupt(out, scans)
        # Every plant ran on the external worker process, none in this test process.
        assert {r["worker"] for r in rows} == worker_addresses
    finally:
        for proc in (worker, scheduler):
            if proc is not None:
                _stop(proc)
