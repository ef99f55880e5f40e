"""Cluster launcher settings refused at plan time, before anything is written (cluster_batches.check_sbatch,
check_ray; plan.plan_sweep's task numbers for every submitit launch), and the driver's lines for a launch that a
cluster ended (launch._launcher_error, a SIGTERM that ray.init's handler took). No cluster: a fake `sbatch` on PATH
answers --test-only, and a closed local port stands for an unreachable Ray head."""

from __future__ import annotations

import os
import signal
import socket
import stat
import sys
import tempfile
from pathlib import Path

import pytest
from typer.testing import CliRunner

from riskplan.cli import app
from riskplan.experiments.sweeping import launch as launch_module
from riskplan.experiments.sweeping.cluster_batches import check_sbatch
from riskplan.experiments.sweeping.launch import _launcher_error, _task_names
from riskplan.experiments.sweeping.launcher_settings import (
    check_own_cpus,
    check_ray,
    parse_ray_address,
    ray_address,
    ray_temp_dir,
    raylet_addresses,
)
from riskplan.experiments.sweeping.plan import plan_sweep
from riskplan.run.compose import parse_overrides
from riskplan.util.errors import BadInput
from riskplan.util.interrupt import Interrupted

pytest.importorskip("hydra_plugins.hydra_submitit_launcher", reason="the slurm extra (submitit) is not installed")

# a stand-in for sbatch: --test-only refuses two settings and arrays over 1001 tasks as Slurm 22.05 words it
# (seen on the test cluster), accepts the rest; each script
# it was given is kept (scripts.log) so that a test can read the #SBATCH lines
FAKE_SBATCH = """#!/bin/sh
[ "$1" = "--test-only" ] || { echo "sbatch: error: this fake takes --test-only only" >&2; exit 9; }
cat "$2" >> "$(dirname "$0")/scripts.log"
if grep -q -- "--partition=nosuch" "$2"; then
  echo "sbatch: error: invalid partition specified: nosuch" >&2
  echo "allocation failure: Invalid partition name specified" >&2; exit 1
fi
if grep -q -- "--cpus-per-task=64" "$2"; then
  echo "allocation failure: Requested node configuration is not available" >&2; exit 1
fi
last=$(sed -n 's/^#SBATCH --array=0-//p' "$2" | cut -d% -f1)
if [ -n "$last" ] && [ "$last" -gt 1000 ]; then  # MaxArraySize=1001, Slurm's default
  echo "allocation failure: Invalid job array specification" >&2; exit 1
fi
echo "sbatch: Job 7 to start at 2026-01-01T00:00:00 using 1 processors on nodes n1 in partition debug" >&2
"""
UNREACHABLE_SBATCH = """#!/bin/sh
echo "sbatch: error: resolve_ctls_from_dns_srv: res_nsearch error: Unknown host" >&2
echo "sbatch: fatal: Could not establish a configuration source" >&2; exit 1
"""
SLOW_SBATCH = "#!/bin/sh\nexec sleep 30\n"


def fake_sbatch(tmp_path: Path, monkeypatch, text: str = FAKE_SBATCH) -> Path:
    """`text` as the only sbatch on PATH; returns its folder."""
    folder = tmp_path / "bin"
    folder.mkdir()
    script = folder / "sbatch"
    script.write_text(text)
    script.chmod(script.stat().st_mode | stat.S_IXUSR)
    monkeypatch.setenv("PATH", f"{folder}:/usr/bin:/bin")
    return folder


def overrides(*items: str) -> dict:
    return {o.key_or_group: o for o in parse_overrides(list(items))}


# ------------------------------------------------------------------------------------------------- sbatch


def test_a_setting_sbatch_refuses_is_bad_input_naming_its_key(tmp_path, monkeypatch):
    folder = fake_sbatch(tmp_path, monkeypatch)
    keys = overrides("hydra.launcher.partition=nosuch", "hydra.launcher.timeout_min=10", "hydra.launcher.mem_gb=4")
    with pytest.raises(BadInput) as refused:
        check_sbatch("submitit_slurm", keys)
    assert str(refused.value) == (
        "hydra.launcher.partition: sbatch refuses it: invalid partition specified: nosuch (sbatch --test-only); "
        "give settings this cluster accepts (sinfo lists its partitions and nodes)"
    )
    # the script sbatch judged is submitit's, from the launcher's settings, as an array
    script = (folder / "scripts.log").read_text()
    for line in ("#SBATCH --time=10", "#SBATCH --mem=4GB", "#SBATCH --array=0-1%2", "#SBATCH --signal=USR2@120"):
        assert line in script


def test_only_the_keys_without_which_sbatch_accepts_are_named(tmp_path, monkeypatch):
    fake_sbatch(tmp_path, monkeypatch)
    keys = overrides("hydra.launcher.partition=debug", "hydra.launcher.cpus_per_task=64", "hydra.launcher.qos=normal")
    with pytest.raises(BadInput, match=r"^hydra\.launcher\.cpus_per_task: sbatch refuses it: allocation failure: "):
        check_sbatch("submitit_slurm", keys)
    keys = overrides("hydra.launcher.partition=debug", "+hydra.launcher.additional_parameters={cpus-per-task:64}")
    with pytest.raises(BadInput, match=r"^hydra\.launcher\.additional_parameters: "):
        check_sbatch("submitit_slurm", keys)


def test_settings_sbatch_accepts_pass(tmp_path, monkeypatch):
    fake_sbatch(tmp_path, monkeypatch)
    check_sbatch("submitit_slurm", overrides("hydra.launcher.partition=debug", "hydra.launcher.cpus_per_task=2"))
    check_sbatch("submitit_slurm", {})
    check_sbatch("submitit_local", overrides("hydra.launcher.partition=nosuch"))  # no SLURM: not sbatch's


def test_sbatch_judges_the_array_the_sweep_submits(tmp_path, monkeypatch):
    folder = fake_sbatch(tmp_path, monkeypatch)
    check_sbatch("submitit_slurm", {}, tasks=1)  # one job: submitit submits it without --array
    assert "--array" not in (folder / "scripts.log").read_text()
    check_sbatch("submitit_slurm", {}, tasks=1001)
    assert "#SBATCH --array=0-1000%256" in (folder / "scripts.log").read_text()  # array_parallelism's default
    with pytest.raises(BadInput) as refused:
        check_sbatch("submitit_slurm", overrides("hydra.launcher.partition=debug"), tasks=1002)
    assert str(refused.value) == (
        "hydra/launcher=submitit_slurm: sbatch refuses a job array of 1002 tasks, one a job: allocation failure: "
        "Invalid job array specification (sbatch --test-only), and takes a smaller one (the cluster's MaxArraySize: "
        "scontrol show config); sweep fewer jobs at once, or give --batch (a task per chunk of jobs)"
    )
    with pytest.raises(BadInput, match=r"^hydra\.launcher\.partition: sbatch refuses it: invalid partition"):
        check_sbatch("submitit_slurm", overrides("hydra.launcher.partition=nosuch"), tasks=1002)  # not the size


@pytest.mark.parametrize(("sweep", "array"), [("seed=0,1,2", "--array=0-2%3"), ("seed=0", None)])
def test_the_plan_asks_sbatch_about_the_array_of_its_jobs(tmp_path, monkeypatch, sweep, array):
    folder = fake_sbatch(tmp_path, monkeypatch)
    plan_sweep([sweep, "hydra/launcher=submitit_slurm"])
    script = (folder / "scripts.log").read_text()
    assert (f"#SBATCH {array}" in script) if array else ("--array" not in script)


@pytest.mark.parametrize("text", [UNREACHABLE_SBATCH, None], ids=["no controller", "no sbatch"])
def test_no_verdict_without_a_controller_or_without_sbatch(tmp_path, monkeypatch, text):
    if text is None:
        (tmp_path / "bin").mkdir()
        monkeypatch.setenv("PATH", str(tmp_path / "bin"))
    else:
        fake_sbatch(tmp_path, monkeypatch, text)
    check_sbatch("submitit_slurm", overrides("hydra.launcher.partition=nosuch"))


def test_an_sbatch_that_does_not_answer_in_time_gives_no_verdict(tmp_path, monkeypatch):
    fake_sbatch(tmp_path, monkeypatch, SLOW_SBATCH)
    check_sbatch("submitit_slurm", overrides("hydra.launcher.partition=nosuch"), timeout=0.2)


def test_settings_hydra_refuses_are_left_to_hydra(tmp_path, monkeypatch):
    fake_sbatch(tmp_path, monkeypatch)  # an unknown key or a bad type: Hydra's own line names it, later
    check_sbatch("submitit_slurm", overrides("hydra.launcher.partition=nosuch", "hydra.launcher.nosuch=1"))
    check_sbatch("submitit_slurm", overrides("hydra.launcher.partition=nosuch", "hydra.launcher.nodes=abc"))


@pytest.mark.slow  # the CLI plans the sweep: about 2 s
@pytest.mark.parametrize("batch", [[], ["--batch"]], ids=["jobs", "batch"])
def test_the_sweep_command_refuses_it_with_exit_2_and_writes_nothing(tmp_path, monkeypatch, batch):
    fake_sbatch(tmp_path, monkeypatch)
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    args = ["sweep", "seed=0,1", "hydra/launcher=submitit_slurm", "hydra.launcher.partition=nosuch", *batch]
    result = CliRunner().invoke(app, [*args, f"hydra.sweep.dir={work / 'sweep'}"])
    assert result.exit_code == 2, result.output
    assert result.stderr.strip() == (
        "error: hydra.launcher.partition: sbatch refuses it: invalid partition specified: nosuch (sbatch "
        "--test-only); give settings this cluster accepts (sinfo lists its partitions and nodes)"
    )
    assert list(work.iterdir()) == []


# ------------------------------------------------------------------------------------------------- task numbers


@pytest.mark.parametrize("launcher", ["submitit_slurm", "submitit_local"])
@pytest.mark.parametrize(
    ("setting", "line"),
    [
        ("timeout_min=0", "hydra.launcher.timeout_min: got 0; expected a whole number of at least 1"),
        ("mem_gb=-1", "hydra.launcher.mem_gb: got -1; expected a whole number of at least 1"),
        ("cpus_per_task=0", "hydra.launcher.cpus_per_task: got 0; expected a whole number of at least 1"),
    ],
)
def test_launcher_numbers_are_checked_without_batch_too(tmp_path, monkeypatch, launcher, setting, line):
    monkeypatch.setenv("PATH", str(tmp_path))  # no sbatch: the check is riskplan's own
    with pytest.raises(BadInput) as refused:
        plan_sweep(["seed=0,1", f"hydra/launcher={launcher}", f"hydra.launcher.{setting}"])
    assert str(refused.value) == line


# ------------------------------------------------------------------------------------------------- Ray


@pytest.fixture
def closed_port() -> int:
    """A local port where nothing listens (bound, then released)."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def test_an_unreachable_ray_address_is_bad_input(closed_port):
    keys = overrides(f"+hydra.launcher.ray.init.address=127.0.0.1:{closed_port}")
    with pytest.raises(BadInput, match=rf"^hydra\.launcher\.ray\.init\.address: no Ray cluster answers at "
                       rf"127\.0\.0\.1:{closed_port} \("):  # fmt: skip
        check_ray("ray", keys, environ={})
    # ray_cluster's `auto`, and `auto` given to the ray launcher, take RAY_ADDRESS, as ray.init does (the ray
    # launcher's unset address is made local: test_a_local_ray_instance_has_no_address_to_check)
    for launcher, keys in (("ray_cluster", {}), ("ray", overrides("+hydra.launcher.ray.init.address=auto"))):
        with pytest.raises(BadInput, match=rf"^RAY_ADDRESS: no Ray cluster answers at 127\.0\.0\.1:{closed_port} "):
            check_ray(launcher, keys, environ={"RAY_ADDRESS": f"127.0.0.1:{closed_port}"})


def test_a_reachable_ray_address_passes():
    with socket.socket() as head:
        head.bind(("127.0.0.1", 0))
        head.listen()
        port = head.getsockname()[1]
        check_ray("ray_cluster", overrides(f"hydra.launcher.ray.init.address=127.0.0.1:{port}"), environ={})
        check_ray("ray_cluster", {}, environ={"RAY_ADDRESS": f"127.0.0.1:{port}"})
        # a cluster's nodes are its own: CPUs per job are not judged by this machine's
        check_ray(
            "ray_cluster", overrides("+hydra.launcher.ray.remote.num_cpus=64"), {"RAY_ADDRESS": f"127.0.0.1:{port}"}
        )


def test_a_local_ray_instance_has_no_address_to_check(tmp_path):
    assert ray_address("ray", {}, {}) == (None, "hydra.launcher.ray.init.address")
    assert ray_address("ray", {}, {"RAY_ADDRESS": "127.0.0.1:1"})[0] is None  # made local: RAY_ADDRESS is not read
    assert ray_address("ray", overrides("+hydra.launcher.ray.init.address=local"), {"RAY_ADDRESS": "x:1"})[0] is None
    assert ray_address("ray_cluster", {}, {}) == ("auto", "hydra.launcher.ray.init.address")  # looked for here
    check_ray("ray", {}, environ={"RAY_TMPDIR": str(tmp_path)}, proc=str(fake_proc(tmp_path)))  # nothing runs


# `auto` (ray_cluster's default) without RAY_ADDRESS: Ray's temp dir (RAY_TMPDIR) and process table (proc) faked


def fake_proc(tmp_path: Path, *cmdlines: bytes) -> Path:
    """A process table holding these command lines (NUL-separated, as Linux writes them), and a shell's."""
    proc = tmp_path / "proc"
    for pid, cmdline in enumerate((b"/bin/bash\0-l\0", *cmdlines), start=100):
        (proc / str(pid)).mkdir(parents=True)
        (proc / str(pid) / "cmdline").write_bytes(cmdline)
    (proc / "self").mkdir()  # not a pid
    return proc


def raylet(address: str) -> bytes:
    return f"/venv/lib/python3.11/site-packages/ray/core/src/ray/raylet/raylet\0--gcs-address={address}\0".encode()


def recorded(tmp_path: Path, address: str) -> dict:
    """The environment of a machine whose last `ray start` recorded `address` under RAY_TMPDIR."""
    (tmp_path / "ray").mkdir()
    (tmp_path / "ray" / "ray_current_cluster").write_text(address + "\n")
    return {"RAY_TMPDIR": str(tmp_path)}


def test_auto_that_finds_no_ray_instance_is_bad_input(tmp_path):
    proc = fake_proc(tmp_path, b"/usr/bin/python3\0worker.py\0--gcs-address=10.0.0.1:6379\0")  # not a raylet
    with pytest.raises(BadInput) as refused:
        check_ray("ray_cluster", {}, environ={"RAY_TMPDIR": str(tmp_path)}, proc=str(proc))
    assert str(refused.value) == (
        f"hydra.launcher.ray.init.address: auto found no running Ray instance on this machine (no {tmp_path}/ray/"
        f"ray_current_cluster, no raylet process); start one (ray start --head) or give HOST:PORT of a cluster's "
        f"head (or RAY_ADDRESS)"
    )
    with pytest.raises(BadInput, match=r"^RAY_ADDRESS: auto found no running Ray instance"):  # as Ray reads it
        check_ray("ray_cluster", {}, environ={"RAY_TMPDIR": str(tmp_path), "RAY_ADDRESS": "auto"}, proc=str(proc))
    check_ray("ray_cluster", {}, environ={"RAY_TMPDIR": str(tmp_path)}, proc=str(tmp_path / "none"))  # no /proc


def test_auto_takes_the_address_ray_start_recorded(tmp_path, closed_port):
    environ = recorded(tmp_path, f"127.0.0.1:{closed_port}")
    with pytest.raises(BadInput) as refused:
        check_ray("ray_cluster", {}, environ=environ, proc=str(fake_proc(tmp_path)))
    assert str(refused.value) == (
        f"hydra.launcher.ray.init.address: no Ray cluster answers at 127.0.0.1:{closed_port} (Connection refused; "
        f"auto read it from {tmp_path}/ray/ray_current_cluster); start one there (ray start --head "
        f"--port={closed_port}) or give the address of the head node's `ray start`"
    )


def test_auto_passes_where_the_recorded_head_answers(tmp_path):
    with socket.socket() as head:
        head.bind(("127.0.0.1", 0))
        head.listen()
        environ = recorded(tmp_path, f"127.0.0.1:{head.getsockname()[1]}")
        check_ray("ray_cluster", {}, environ=environ, proc=str(fake_proc(tmp_path)))
        keys = overrides("+hydra.launcher.ray.init.address=auto")
        check_ray("ray", keys, environ=environ, proc=str(fake_proc(tmp_path / "other")))


def test_auto_takes_a_running_raylets_address(tmp_path, closed_port):
    with socket.socket() as head:
        head.bind(("127.0.0.1", 0))
        head.listen()
        proc = fake_proc(tmp_path, raylet(f"127.0.0.1:{head.getsockname()[1]}"))
        check_ray("ray_cluster", {}, environ={"RAY_TMPDIR": str(tmp_path)}, proc=str(proc))
    proc = fake_proc(tmp_path / "dead", raylet(f"127.0.0.1:{closed_port}"))
    with pytest.raises(BadInput, match=rf"at 127\.0\.0\.1:{closed_port} \(Connection refused; auto took it from a "
                       r"running raylet's --gcs-address\); "):  # fmt: skip
        check_ray("ray_cluster", {}, environ={"RAY_TMPDIR": str(tmp_path)}, proc=str(proc))


def test_raylet_addresses_reads_command_lines_as_ray_does(tmp_path):
    proc = fake_proc(
        tmp_path,
        raylet("10.0.0.2:6379"),
        b"/opt/ray/raylet --node_id=x --gcs-address=10.0.0.1:6379 --store_socket_name=s\0",  # a title, one string
        b"/opt/ray/raylet\0--gcs-address=None\0",  # Ray's placeholder, skipped as Ray skips it
        b"gcs_server\0--gcs-address=10.0.0.9:1\0",
        b"",  # a kernel thread or a zombie
    )
    assert raylet_addresses(str(proc)) == ["10.0.0.1:6379", "10.0.0.2:6379"]
    assert raylet_addresses(str(tmp_path / "none")) is None


def test_rays_temp_dir_is_found_as_ray_finds_it(tmp_path):
    assert ray_temp_dir({}, {"RAY_TMPDIR": "/a", "TMPDIR": "/b"}) == "/a/ray"
    assert ray_temp_dir({}, {"TMPDIR": "/b"}) == ("/b/ray" if sys.platform.startswith("linux") else "/tmp/ray")
    assert ray_temp_dir({}, {}) in ("/tmp/ray", os.path.join(tempfile.gettempdir(), "ray"))
    assert ray_temp_dir(overrides("+hydra.launcher.ray.init._temp_dir=/c"), {"RAY_TMPDIR": "/a"}) == "/c"


@pytest.mark.parametrize("address", ["nonsense", "host:", "host:abc", "host:70000", "a:b:c", "http://h:1"])
def test_a_malformed_ray_address_is_bad_input(address):
    with pytest.raises(BadInput, match=r"^hydra\.launcher\.ray\.init\.address: got .*; expected HOST:PORT"):
        check_ray("ray", overrides(f"+hydra.launcher.ray.init.address='{address}'"), environ={})


def test_ray_address_forms():
    key = "hydra.launcher.ray.init.address"
    assert parse_ray_address("10.0.0.1:6379", key) == ("10.0.0.1", 6379)
    assert parse_ray_address("head-node:6379", key) == ("head-node", 6379)
    assert parse_ray_address("ray://head:10001", key) == ("head", 10001)
    assert parse_ray_address("[::1]:6379", key) == ("::1", 6379)


def test_an_unknown_ray_remote_option_is_bad_input():
    with pytest.raises(BadInput, match=r"^hydra\.launcher\.ray\.remote\.nosuch: ray\.remote has no option 'nosuch'"):
        check_ray("ray", overrides("+hydra.launcher.ray.remote.nosuch=1"), environ={})
    with pytest.raises(BadInput, match=r"^hydra\.launcher\.ray\.remote\.foo: ray\.remote has no option 'foo'"):
        check_ray("ray", overrides("+hydra.launcher.ray.remote={num_cpus:1,foo:2}"), environ={})
    check_ray("ray", overrides("+hydra.launcher.ray.remote.num_cpus=2", "+hydra.launcher.ray.remote.memory=9"), {})
    check_ray("ray", overrides("+hydra.launcher.ray.remote.resources.disk=1"), environ={})


@pytest.mark.parametrize(
    ("settings", "line"),
    [
        (["remote.num_cpus=3"], "got 3; the sweep's own Ray instance has 2 CPUs (this machine's)"),
        (["remote={num_cpus:2.5}"], "got 2.5; the sweep's own Ray instance has 2 CPUs (this machine's)"),
        (
            ["remote.num_cpus=2", "init.num_cpus=1"],
            "got 2; the sweep's own Ray instance has 1 CPU (hydra.launcher.ray.init.num_cpus)",
        ),
        (["remote.num_cpus=2"], None),
        (["remote.num_cpus=8", "init.num_cpus=8"], None),  # Ray takes more CPUs than the machine has, if told so
    ],
)
def test_a_job_asking_the_sweep_s_own_ray_instance_for_more_cpus_than_it_has_is_bad_input(settings, line):
    """Ray would leave it pending for ever (an infeasible task)."""
    keys = overrides(*(f"+hydra.launcher.ray.{setting}" for setting in settings))
    if line is None:
        check_own_cpus(keys, machine=2)
        return
    with pytest.raises(BadInput) as refused:
        check_own_cpus(keys, machine=2)
    assert str(refused.value).startswith(f"hydra.launcher.ray.remote.num_cpus: {line}, and a job asking for more ")


# ray.remote's verdicts on these values (Ray 2.60's validate_task_options, run on each in the Ray environment)
@pytest.mark.parametrize(
    ("setting", "takes"),
    [
        ("num_cpus=-1", "0, a number of at least 0.0001, or null"),
        ("num_cpus=0.00001", "0, a number of at least 0.0001, or null"),  # below Ray's resource unit
        ("num_cpus=inf", "0, a number of at least 0.0001, or null"),
        ("num_cpus=abc", "0, a number of at least 0.0001, or null"),
        ("object_store_memory=1.5", "a whole number of at least 0, or null"),
        ("max_retries=-2", "a whole number of at least -1, or null"),
        ("max_calls=-1", "a whole number of at least 0, or null"),
        ("resources.GPU=1", "CPUs and GPUs as num_cpus and num_gpus, not among resources"),
        ("resources.disk=-1", "0, a number of at least 0.0001, or null"),
        ("resources=3", "a mapping of resource names to quantities"),
        ("num_cpus=0.00015", None),
        ("num_cpus=0", None),
        ("num_gpus=0.5", None),
        ("memory=1.5", None),
        ("max_retries=-1", None),
        ("num_cpus=null", None),
        ("resources={disk:0.5}", None),
    ],
)
def test_a_ray_remote_value_ray_refuses_is_bad_input(setting, takes):
    keys = overrides(f"+hydra.launcher.ray.remote.{setting}")
    if takes is None:
        check_ray("ray", keys, environ={})
        return
    key = setting.split("=")[0]
    with pytest.raises(BadInput) as refused:
        check_ray("ray", keys, environ={})
    assert str(refused.value).startswith(f"hydra.launcher.ray.remote.{key}: got ") and str(refused.value).endswith(
        f"; ray.remote takes {takes}"
    )


# ------------------------------------------------------------------------------------------------- the driver's lines


NOT_REQUEUED_LOG = """Traceback (most recent call last):
  File "riskplan/experiments/sweeping/cluster_batches.py", line 197, in _on_submitit
submitit.core.utils.FailedJobError: Job (task=0) failed during processing with trace:
----------------------
riskplan.util.interrupt.Interrupted: interrupted by SIGUSR2 after 2474 iterations, all checkpointed
  File "submitit/core/job_environment.py", line 227, in checkpoint_and_try_requeue
    raise utils.UncompletedJobError(message)
submitit.core.utils.UncompletedJobError: Job not requeued because: timed-out too many times.

----------------------
You can check full logs with 'job.stderr(0)' and 'job.stdout(0)'or at paths:
  - /sweep/.submitit/34_1/34_1_0_log.err
  - /sweep/.submitit/34_1/34_1_0_log.out
"""


def test_a_job_out_of_requeues_is_named(tmp_path):
    log = tmp_path / "sweep.log"
    log.write_text(NOT_REQUEUED_LOG)
    error = _launcher_error(log, _task_names(tmp_path, [["seed=0"], ["seed=1"]]))
    assert error == (
        f"the launcher stopped: SLURM job 34_1 (seed=1) ended without a result, not requeued: timed-out too many "
        f"times (hydra.launcher.max_num_timeout; submitit's UncompletedJobError; see {log})"
    )
    log.write_text(NOT_REQUEUED_LOG.split("----------------------\nYou")[0])  # without the paths: not named
    assert "a SLURM job ended without a result, not requeued: timed-out too many times" in _launcher_error(log, [])


def test_a_log_line_that_is_no_error_is_never_quoted_as_one(tmp_path):
    log = tmp_path / "sweep.log"
    log.write_text("2026-11-29 21:06:25,921\tINFO worker.py:2038 -- Connected to Ray cluster.\n")
    assert _launcher_error(log, []) == f"the launcher stopped: no error message (see {log})"


def test_a_sigterm_that_ray_init_took_is_the_sweep_interrupted(tmp_path, monkeypatch):
    def ray_like_multirun(args):  # ray.init's handler: sys.exit(signum); then a SIGTERM came
        signal.signal(signal.SIGTERM, lambda signum, frame: None)
        raise SystemExit(signal.SIGTERM)

    monkeypatch.setattr(launch_module, "run_multirun", ray_like_multirun)
    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(Interrupted) as stopped:
        launch_module.launch(["-m"], tmp_path / "sweep.log", [["seed=0"]])
    assert stopped.value.exit_code == 143
    assert signal.getsignal(signal.SIGTERM) == before  # the driver's own handler is back for the summary
    assert not (tmp_path / launch_module.JOB_LIST).exists()
