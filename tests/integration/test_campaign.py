"""The campaign engine (sitl.campaign): records written as runs end, resuming, failures kept, a
worker's death on a real Dask cluster, and the command line flying real flights on a local
cluster and on a separately started scheduler with its workers."""

import json
import os
import signal
import subprocess
import sys
from contextlib import nullcontext
from pathlib import Path

import pytest

from sitl.campaign.cluster import DaskExecutor, connect
from sitl.campaign.engine import Campaign, Job, SerialExecutor

from .. import campaign_jobs as jobs
from ..paths import ROOT
from ..waits import wait_for


def _jobs(fn, xs, *extra):
    return [Job(f"x={x}", Path(f"x-{x}"), fn, (x, *extra), {"x": x}) for x in xs]


def _serial():
    return nullcontext(SerialExecutor())


def test_each_run_is_recorded_as_it_ends_and_a_second_run_skips_the_finished(tmp_path):
    counts = []
    result = Campaign(tmp_path, _jobs(jobs.fail_at, [1.0, 2.0, 3.0], 2.0)).run(_serial, progress=counts.append)
    assert [r["status"] for r in result.records] == ["ok", "failed", "ok"]
    assert result.records[1]["error"] == "RuntimeError: refused 2.0"
    assert "RuntimeError" in (tmp_path / "x-2.0" / "error.txt").read_text()
    assert result.records[2]["result"] == {"x": 3.0, "y": 9.0, "per_link": [3.0, 6.0]}
    assert counts[-1] == {"done": 3, "running": 0, "failed": 1, "lost": 0, "total": 3}
    on_disk = json.loads((tmp_path / "x-3.0" / "run_record.json").read_text())
    assert on_disk["status"] == "ok" and on_disk["attempts"] == 1 and on_disk["columns"] == {"x": 3.0}
    again = Campaign(tmp_path, _jobs(jobs.fail_at, [1.0, 2.0, 3.0], 5.0)).run(_serial)
    assert (again.skipped, again.ran) == (2, 1)  # the failed run is flown again, the others are not
    assert [r["status"] for r in again.records] == ["ok", "ok", "ok"]


def test_an_interrupted_campaign_goes_on_where_it_stopped(tmp_path):
    with pytest.raises(KeyboardInterrupt):
        Campaign(tmp_path, _jobs(jobs.interrupt_at, [1.0, 2.0, 3.0, 4.0], 3.0)).run(_serial)
    assert sorted(p.parent.name for p in tmp_path.glob("*/run_record.json")) == ["x-1.0", "x-2.0"]
    resumed = Campaign(tmp_path, _jobs(jobs.interrupt_at, [1.0, 2.0, 3.0, 4.0], None)).run(_serial)
    assert (resumed.skipped, resumed.ran) == (2, 2)
    assert resumed.counts() == {"ok": 4, "failed": 0, "lost": 0, "not run": 0}


def test_a_record_of_another_run_in_the_folder_does_not_count_as_finished(tmp_path):
    Campaign(tmp_path, _jobs(jobs.square, [1.0])).run(_serial)
    other = [Job("x=other", Path("x-1.0"), jobs.square, (7.0,))]
    assert Campaign(tmp_path, other).run(_serial).ran == 1


def test_a_worker_that_dies_loses_only_its_run_which_is_flown_again(tmp_path):
    """A real local Dask cluster of two workers: one job kills its worker once, one every time;
    the first is retried and recorded with two attempts, the second recorded lost, the others
    finish as if nothing happened."""
    work = (_jobs(jobs.square, [1.0, 2.0]) + [Job("once", Path("once"), jobs.die_once, (3.0,))]
            + [Job("always", Path("always"), jobs.die_always, (4.0,))] + _jobs(jobs.square, [5.0]))
    with connect(workers=2, retries=1) as client:
        result = Campaign(tmp_path, work).run(lambda: nullcontext(DaskExecutor(client)))
    by = {r["key"]: r for r in result.records}
    assert all(by[k]["status"] == "ok" and by[k]["attempts"] == 1 for k in ("x=1.0", "x=2.0", "x=5.0"))
    assert by["once"]["status"] == "ok" and by["once"]["attempts"] == 2 and by["once"]["result"]["y"] == 9.0
    assert by["always"]["status"] == "lost" and "KilledWorker" in by["always"]["error"]
    assert by["always"]["attempts"] == 2
    assert result.counts() == {"ok": 4, "failed": 0, "lost": 1, "not run": 0}


def _campaign_cmd(out, *where):
    # a 1 s take-off (a setting like the swept one) so that 4 s flights have a window for their metrics
    return [sys.executable, "-m", "sitl", "campaign", "run", "--config", "configs/sitl/chain/three_link.toml",
            "--set", "firmware.ekf.gate_sigma=3,5", "--set", "trajectory.takeoff_duration_s=1", "--seeds", "0-1",
            "--duration", "4", "--quiet", "--out", str(out), *where]


def _campaign(out, *where):
    res = subprocess.run(_campaign_cmd(out, *where), cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    return res.stdout


def _interrupted_campaign(out, *where) -> int:
    """The campaign stopped as Ctrl-C in a terminal stops it (SIGINT to its whole process group,
    workers included) once a run has finished; how many runs had."""
    # (SIGINT as a terminal leaves it: a suite started in the background inherits it ignored)
    proc = subprocess.Popen(_campaign_cmd(out, *where), cwd=ROOT, start_new_session=True, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        assert wait_for(lambda: any(out.glob("*/*/seed-*/run_record.json")) or proc.poll() is not None, 120.0)
        os.killpg(proc.pid, signal.SIGINT)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 130 and "the same command goes on where this one stopped" in err, err[-3000:]
    records = [json.loads(p.read_text()) for p in out.glob("*/*/seed-*/run_record.json")]
    assert records and all(r["status"] == "ok" for r in records)  # an interrupted run is not recorded
    return len(records)


def test_the_same_campaign_on_a_local_cluster_and_on_a_scheduler_gives_the_same_table(tmp_path, dask_cluster):
    """Real flights (three_link, 4 s, two settings x two seeds): the local cluster, interrupted
    with Ctrl-C and started again, and a separately started scheduler with two workers give the
    same table to the last digit."""
    finished = _interrupted_campaign(tmp_path / "local", "--workers", "2")
    out = _campaign(tmp_path / "local", "--workers", "2")
    assert f"{finished} finished before, {4 - finished} now" in out and "(4 ok, 0 failed, 0 lost)" in out
    _campaign(tmp_path / "remote", "--scheduler", dask_cluster)
    table = (tmp_path / "local" / "results.csv").read_text().splitlines()
    assert len(table) == 5 and table[0].startswith(
        "scenario,mode,set:firmware.ekf.gate_sigma,set:trajectory.takeoff_duration_s,duration_s,seed,status")
    diff = subprocess.run([sys.executable, "-m", "sitl", "campaign", "diff", str(tmp_path / "local" / "results.csv"),
                           str(tmp_path / "remote" / "results.csv")], cwd=ROOT, capture_output=True, text=True)
    assert diff.returncode == 0 and "identical" in diff.stdout, diff.stdout
    remote = (tmp_path / "remote" / "results.csv").read_text()
    assert "tcp://127.0.0.1:" in remote  # the workers named in the table
    summary = (tmp_path / "local" / "summary.md").read_text()
    assert "three_link batch duration_s=4.0 firmware.ekf.gate_sigma=3 trajectory.takeoff_duration_s=1" in summary
    assert (tmp_path / "local" / "plots" / "rms_track_true_m.png").stat().st_size > 1000
    nees = json.loads((tmp_path / "local" / "nees.json").read_text())
    assert len(nees) == 2 and all(len(g["seeds"]) == 2 for g in nees.values())


@pytest.mark.parametrize("args, message", [
    (["faults", "--flights", "2", "--mode", "batch", "--speed", "1"], "speed paces fleet flights"),
    (["run", "--seeds", "0", "--speed", "1"], "speed paces fleet flights"),
    (["faults", "--flights", "2", "--speed", "-1"], "the pace must be >= 0"),
    (["faults", "--flights", "2", "--speed", "fast"], "is not a number")])
def test_a_pace_batch_mode_cannot_have_is_refused_before_anything_flies(tmp_path, args, message):
    cmd = [sys.executable, "-m", "sitl", "campaign", args[0], "--config", "configs/sitl/chain/three_link.toml",
           *args[1:], "--quiet", "--out", str(tmp_path / "c")]
    res = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert res.returncode == 2 and message in res.stderr, res.stderr
    assert not (tmp_path / "c").exists()


def test_a_campaign_with_a_bad_setting_stops_before_anything_flies(tmp_path):
    cmd = [sys.executable, "-m", "sitl", "campaign", "run", "--config", "configs/sitl/chain/three_link.toml",
           "--set", "firmware.ekf.gate_sigm=3,5", "--seeds", "0-1", "--quiet", "--out", str(tmp_path / "c")]
    res = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert res.returncode == 2 and "firmware.ekf.gate_sigm: unknown key (did you mean 'gate_sigma'?)" in res.stderr
    assert not (tmp_path / "c").exists()


def test_a_random_fault_campaign_flies_its_schedules_and_reports_per_kind(tmp_path):
    """python -m sitl campaign faults in batch mode: two three_link flights with schedules drawn
    from the seed, faults.json with every flight's events and figures, faults.md with the per-kind
    table and each crash's replay command; the same command again flies nothing."""
    out = tmp_path / "faults"
    cmd = [sys.executable, "-m", "sitl", "campaign", "faults", "--config", "configs/sitl/chain/three_link.toml",
           "--flights", "2", "--seed", "1", "--mode", "batch", "--serial", "--duration", "18", "--quiet",
           "--out", str(out)]
    res = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    report = json.loads((out / "faults.json").read_text())
    assert report["flights"] == 2 and [r["status"] for r in report["runs"]] == ["ok", "ok"]
    kinds = {e["kind"] for r in report["runs"] for e in r["events"]}
    assert kinds and not kinds & {"mavlink_loss", "companion_kill"} and set(report["table"]) == kinds
    for r in report["runs"]:
        assert (out / r["folder"] / "metrics.json").exists() and f"--seed {r['seed']}" in r["replay"]
        assert all("track_during_m" in e for e in r["events"])
    text = (out / "faults.md").read_text()
    assert "| kind | flights |" in text and f"## Crashes ({sum(r['crashed'] for r in report['runs'])})" in text
    again = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert again.returncode == 0 and json.loads((out / "faults.json").read_text())["table"] == report["table"]
