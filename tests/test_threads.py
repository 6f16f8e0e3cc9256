"""Thread pools sized to the cores this process may use: GCGS_THREADS, CPU affinity, cgroup quota."""
from __future__ import annotations

import os

import pytest

from pipeline import cli, threads
from pipeline.errors import ConfigError
from pipeline.threads import available_cores, configure_threads


def _cgroup(root, rel: str, text: str):
    path = root / "sys" / "fs" / "cgroup" / rel
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)


# --- GCGS_THREADS ---------------------------------------------------------------------------

def test_env_overrides_affinity_and_quota(tmp_path):
    _cgroup(tmp_path, "cpu.max", "100000 100000")
    assert available_cores({"GCGS_THREADS": "3"}, tmp_path, affinity=2) == (3, "GCGS_THREADS=3")


@pytest.mark.parametrize("value", ["0", "abc", "-1", "", "1.5", "2 threads"])
def test_bad_env_value_is_a_one_line_config_error(tmp_path, value):
    with pytest.raises(ConfigError) as info:
        available_cores({"GCGS_THREADS": value}, tmp_path, affinity=4)
    message = str(info.value)
    assert "GCGS_THREADS" in message and repr(value) in message and "\n" not in message


# --- affinity ---------------------------------------------------------------------------------

def test_affinity_smaller_than_cpu_count(monkeypatch, tmp_path):
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 3}, raising=False)
    monkeypatch.setattr(os, "cpu_count", lambda: 8)
    n, reason = available_cores({}, tmp_path)
    assert n == 2 and "affinity" in reason and "8" in reason


def test_cpu_count_where_affinity_is_unavailable(monkeypatch, tmp_path):
    monkeypatch.delattr(os, "sched_getaffinity", raising=False)
    monkeypatch.setattr(os, "cpu_count", lambda: 5)
    assert available_cores({}, tmp_path)[0] == 5


def test_never_less_than_one(tmp_path):
    assert available_cores({}, tmp_path, affinity=0)[0] == 1


def test_real_machine_gives_at_least_one_core():
    n, reason = available_cores({})
    assert n >= 1 and reason


# --- cgroup quota -----------------------------------------------------------------------------

@pytest.mark.parametrize("text, expected", [
    ("150000 100000\n", 2),   # 1.5 CPUs: rounded up
    ("200000 100000\n", 2),
    ("50000 100000\n", 1),    # half a CPU: never less than 1
    ("max 100000\n", 8),      # no quota
])
def test_cgroup_v2_quota(tmp_path, text, expected):
    _cgroup(tmp_path, "cpu.max", text)
    n, reason = available_cores({}, tmp_path, affinity=8)
    assert n == expected
    assert ("cpu.max" in reason) == (expected < 8)


@pytest.mark.parametrize("text", ["", "garbage", "abc 100000", "150000", "150000 0", "0 100000", "-5 100000",
                                  "1 2 3"])
def test_garbled_cgroup_v2_file_is_ignored(tmp_path, text):
    _cgroup(tmp_path, "cpu.max", text)
    assert available_cores({}, tmp_path, affinity=8) == (8, "CPU affinity (8 CPUs)")


def test_unreadable_cgroup_file_is_ignored(tmp_path):
    (tmp_path / "sys" / "fs" / "cgroup" / "cpu.max").mkdir(parents=True)  # a folder: reading fails
    (tmp_path / "sys" / "fs" / "cgroup" / "cpu").mkdir()
    (tmp_path / "sys" / "fs" / "cgroup" / "cpu" / "cpu.cfs_quota_us").write_bytes(b"\xff\xfe2\x00")  # not text
    _cgroup(tmp_path, "cpu/cpu.cfs_period_us", "100000")
    assert available_cores({}, tmp_path, affinity=8)[0] == 8


@pytest.mark.parametrize("quota, period, expected", [
    ("300000\n", "100000\n", 3),
    ("250000\n", "100000\n", 3),
    ("-1\n", "100000\n", 8),
    ("300000\n", None, 8),         # no period file
    ("lots\n", "100000\n", 8),
])
def test_cgroup_v1_quota(tmp_path, quota, period, expected):
    _cgroup(tmp_path, "cpu/cpu.cfs_quota_us", quota)
    if period is not None:
        _cgroup(tmp_path, "cpu/cpu.cfs_period_us", period)
    assert available_cores({}, tmp_path, affinity=8)[0] == expected


def test_cgroup_v1_combined_controller_folder(tmp_path):
    _cgroup(tmp_path, "cpu,cpuacct/cpu.cfs_quota_us", "200000")
    _cgroup(tmp_path, "cpu,cpuacct/cpu.cfs_period_us", "100000")
    assert available_cores({}, tmp_path, affinity=8)[0] == 2


def test_smaller_of_affinity_and_quota(tmp_path):
    _cgroup(tmp_path, "cpu.max", "400000 100000")
    n, reason = available_cores({}, tmp_path, affinity=2)
    assert (n, reason) == (2, "CPU affinity (2 CPUs)")
    n, reason = available_cores({}, tmp_path, affinity=6)
    assert n == 4 and "cgroup" in reason and "sys/fs/cgroup/cpu.max" in reason


def test_quota_of_the_process_own_cgroup_and_its_parents(tmp_path):
    """Without a cgroup namespace (a systemd unit, a SLURM step) the quota sits on the process's
    own cgroup or a parent of it, named in /proc/self/cgroup; the tightest one counts."""
    (tmp_path / "proc" / "self").mkdir(parents=True)
    (tmp_path / "proc" / "self" / "cgroup").write_text("0::/job_7/step_0\n")
    _cgroup(tmp_path, "job_7/cpu.max", "300000 100000")
    _cgroup(tmp_path, "job_7/step_0/cpu.max", "max 100000")
    n, reason = available_cores({}, tmp_path, affinity=8)
    assert n == 3 and "job_7/cpu.max" in reason
    _cgroup(tmp_path, "job_7/step_0/cpu.max", "100000 100000")
    assert available_cores({}, tmp_path, affinity=8)[0] == 1


# --- configure_threads ------------------------------------------------------------------------

@pytest.fixture
def recorded(monkeypatch):
    """numba's and torch's set_num_threads recording their calls instead of acting."""
    numba = pytest.importorskip("numba")
    torch = pytest.importorskip("torch")
    calls = {"numba": [], "torch": []}
    monkeypatch.setattr(numba, "set_num_threads", calls["numba"].append)
    monkeypatch.setattr(torch, "set_num_threads", calls["torch"].append)
    return calls


def test_configure_sizes_both_pools(monkeypatch, recorded):
    import numba
    monkeypatch.setattr(threads, "available_cores", lambda env: (1, "test"))
    assert configure_threads({}) == 1
    assert recorded == {"numba": [1], "torch": [1]}
    assert numba.config.NUMBA_NUM_THREADS >= 1


def test_configure_clamps_numba_to_its_pool(monkeypatch, recorded):
    import numba
    monkeypatch.setattr(threads, "available_cores", lambda env: (64, "test"))
    monkeypatch.setattr(numba.config, "NUMBA_NUM_THREADS", 3)
    assert configure_threads({}) == 3
    assert recorded == {"numba": [3], "torch": [64]}


def test_env_override_is_clamped_for_numba(monkeypatch, recorded):
    import numba
    monkeypatch.setattr(numba.config, "NUMBA_NUM_THREADS", 2)
    env = {"GCGS_THREADS": "5", "NUMBA_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
    assert configure_threads(env) == 2
    assert recorded == {"numba": [2], "torch": [5]}


@pytest.mark.parametrize("var", ["OMP_NUM_THREADS", "MKL_NUM_THREADS"])
def test_torch_left_alone_when_the_user_set_its_threads(monkeypatch, recorded, var):
    monkeypatch.setattr(threads, "available_cores", lambda env: (1, "test"))
    assert configure_threads({var: "4"}) == 1
    assert recorded == {"numba": [1], "torch": []}


def test_numba_keeps_the_user_setting(monkeypatch, recorded):
    import numba
    monkeypatch.setattr(threads, "available_cores", lambda env: (1, "test"))
    assert configure_threads({"NUMBA_NUM_THREADS": "7"}) == numba.get_num_threads()
    assert recorded == {"numba": [], "torch": [1]}


def test_configure_for_real_then_restore():
    numba = pytest.importorskip("numba")
    torch = pytest.importorskip("torch")
    before = numba.get_num_threads(), torch.get_num_threads()
    try:
        assert configure_threads({"GCGS_THREADS": "1"}) == 1
        assert (numba.get_num_threads(), torch.get_num_threads()) == (1, 1)
    finally:
        numba.set_num_threads(before[0])
        torch.set_num_threads(before[1])
    assert (numba.get_num_threads(), torch.get_num_threads()) == before


# --- gcgs --------------------------------------------------------------------------------------

def test_cli_configures_threads_before_a_command(monkeypatch):
    import pipeline.stages.report_index as stage
    order = []
    monkeypatch.setattr(cli, "configure_threads", lambda: order.append("threads"))
    monkeypatch.setattr(stage, "run", lambda args: order.append("run") or 0)
    assert cli.main(["report-index"]) == 0
    assert order == ["threads", "run"]


def test_cli_bad_env_is_one_line(monkeypatch, capsys):
    import pipeline.stages.report_index as stage
    monkeypatch.setenv("GCGS_THREADS", "abc")
    monkeypatch.setattr(stage, "run", lambda args: pytest.fail("ran despite a bad GCGS_THREADS"))
    assert cli.main(["report-index"]) == 1
    assert capsys.readouterr().err == ("gcgs report-index: error: GCGS_THREADS='abc': "
                                       "need a positive whole number of threads\n")


def test_cli_params_does_not_size_threads(monkeypatch):
    import pipeline.stages.params as stage
    monkeypatch.setenv("GCGS_THREADS", "abc")
    monkeypatch.setattr(cli, "configure_threads", lambda: pytest.fail("params sized the thread pools"))
    monkeypatch.setattr(stage, "run", lambda args: 0)
    assert cli.main(["params"]) == 0
