"""localization-tune on several machines through a real PostgreSQL server: two tuners started at once
against a fresh database share one study (every trial completes once, no parameter set twice), then a
third run resumes it.

The server is a throwaway PostgreSQL (initdb + pg_ctl of the Debian package `postgresql`, which
scripts/bootstrap.sh installs for the tests) on 127.0.0.1, a free port, trust authentication, in a
temporary folder; stopped and removed afterwards. Without the server binaries the test fails."""
from __future__ import annotations

import glob
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
from pathlib import Path

import optuna
import pytest

from localization.eval.datasets import sim_bag

PG_BIN_GLOB = "/usr/lib/postgresql/*/bin"
STUDY = "two-machines"

START = """\
particle_filter:
  ros__parameters:
    num_particles: 200
    num_beams_per_particle: 20
    ray_caster: lookup_table
    sigma_hit: 0.025
    motion_a_trans: 0.001
"""
SPACE = "motion_a_trans: {low: 0.02, high: 1.0, log: true}\nsigma_hit: {low: 0.05, high: 0.5, log: true}\n"


def _pg_bin() -> Path:
    """The newest installed PostgreSQL server's bin folder (a clear failure when there is none)."""
    found = [Path(p) for p in glob.glob(PG_BIN_GLOB) if (Path(p) / "initdb").is_file()]
    if not found:
        pytest.fail(f"PostgreSQL server binaries not found ({PG_BIN_GLOB}/initdb): install the Debian package "
                    "postgresql (scripts/bootstrap.sh test installs it)")
    return max(found, key=lambda p: int(p.parent.name) if p.parent.name.isdigit() else 0)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _run(cmd: list, user: str | None, **kw) -> subprocess.CompletedProcess:
    """Run a server command, as ``user`` when given (PostgreSQL refuses to run as root)."""
    full = (["runuser", "-u", user, "--"] if user else []) + [str(c) for c in cmd]
    out = subprocess.run(full, capture_output=True, text=True, timeout=120, **kw)
    assert out.returncode == 0, f"{' '.join(full)} failed:\n{out.stdout}\n{out.stderr}"
    return out


@pytest.fixture(scope="module")
def postgres_url():
    """A fresh database on a throwaway PostgreSQL server: its URL."""
    bin_dir = _pg_bin()
    user = None
    root = Path(tempfile.mkdtemp(prefix="tune-postgres-"))
    if os.geteuid() == 0:  # the server runs as a non-root user: postgres (the Debian package's)
        user = "postgres"
        shutil.chown(root, user, user)
    data = root / "data"
    started = False
    try:
        _run([bin_dir / "initdb", "-D", data, "-U", "postgres", "-A", "trust", "-E", "UTF8", "--no-locale",
              "--no-sync"], user, cwd=root)
        for _ in range(3):  # a port taken between finding it and the server binding it: another one
            port = _free_port()
            out = subprocess.run((["runuser", "-u", user, "--"] if user else [])
                                 + [str(bin_dir / "pg_ctl"), "-D", str(data), "-l", str(root / "server.log"), "-w",
                                    "-t", "60", "-o", f"-h 127.0.0.1 -p {port} -k {root} -F", "start"],
                                 capture_output=True, text=True, timeout=120, cwd=root)
            if out.returncode == 0:
                started = True
                break
        log = (root / "server.log").read_text() if (root / "server.log").is_file() else ""
        assert started, f"the PostgreSQL server did not start:\n{out.stdout}\n{out.stderr}\n{log}"
        _run([bin_dir / "createdb", "-h", "127.0.0.1", "-p", port, "-U", "postgres", "tune"], None, cwd=root)
        yield f"postgresql://postgres@127.0.0.1:{port}/tune"
    finally:
        if started:
            subprocess.run((["runuser", "-u", user, "--"] if user else [])
                           + [str(bin_dir / "pg_ctl"), "-D", str(data), "-m", "fast", "-w", "stop"],
                           capture_output=True, timeout=120, cwd=root)
        shutil.rmtree(root, ignore_errors=True)


@pytest.fixture(scope="module")
def bag() -> str:
    return str(sim_bag("trial1_noise0", duration=3.0))


def _tune(bag, tmp_path: Path, url: str, name: str, trials: int) -> list[str]:
    params, space = tmp_path / "start.yaml", tmp_path / "space.yaml"
    params.write_text(START)
    space.write_text(SPACE)
    return [sys.executable, "-m", "localization.tools.tune", bag, "--map", "stata_basement", "--params", str(params),
            "--space", str(space), "--out", str(tmp_path / name), "--trials", str(trials), "--storage", url,
            "--study", STUDY, "--quiet", "--json"]


def _key(trial) -> tuple:
    return tuple(sorted(trial.params.items()))


def test_two_tuners_at_once_share_a_fresh_database_and_a_third_resumes(postgres_url, bag, tmp_path):
    procs = [subprocess.Popen(_tune(bag, tmp_path, postgres_url, f"machine{k}", 3), stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True) for k in range(2)]
    outputs = [p.communicate(timeout=600) for p in procs]
    for p, (_, err) in zip(procs, outputs):
        assert p.returncode == 0, err
    first = optuna.load_study(study_name=STUDY, storage=postgres_url).get_trials()
    assert sorted(t.number for t in first) == list(range(6))
    assert all(t.state == optuna.trial.TrialState.COMPLETE for t in first), [t.state.name for t in first]
    assert len({_key(t) for t in first}) == 6  # every parameter set evaluated once
    assert not any("repeat_of" in t.user_attrs for t in first)
    assert sum(bool(t.user_attrs.get("baseline")) for t in first) == 1  # the starting parameters queued once
    assert len({t.user_attrs["worker_pid"] for t in first}) == 2  # both tuners ran trials

    third = subprocess.run(_tune(bag, tmp_path, postgres_url, "machine2", 2), capture_output=True, text=True,
                           timeout=600)
    assert third.returncode == 0, third.stderr
    assert json.loads(third.stdout)["n_trials"] == 8
    after = optuna.load_study(study_name=STUDY, storage=postgres_url).get_trials()
    assert sorted(t.number for t in after) == list(range(8))
    kept = {t.number: (_key(t), t.value) for t in after if t.number < 6}
    assert kept == {t.number: (_key(t), t.value) for t in first}  # the earlier trials are kept as they were
    assert all(t.state == optuna.trial.TrialState.COMPLETE for t in after)
    assert len({_key(t) for t in after}) == 8 and not any("repeat_of" in t.user_attrs for t in after)
    assert sum(bool(t.user_attrs.get("baseline")) for t in after) == 1
