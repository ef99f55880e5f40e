"""The launcher's settings riskplan adds to a sweep's command line: its workers (joblib's n_jobs, SLURM's array
parallelism), and the ray.init arguments that fit a local Ray instance or a connection to a cluster. And the Ray
settings a cluster would refuse only once the sweep had begun, checked at plan time (`check_ray`: the address
answers, `auto` finds a Ray instance, ray.remote knows the options; SLURM's are cluster_batches.check_sbatch's)."""

from __future__ import annotations

import math
import os
import re
import socket
import sys
import tempfile

from riskplan.config.validate import check_extra
from riskplan.experiments.sweeping.jobs import LOCAL
from riskplan.util.errors import BadInput
from riskplan.util.limits import cpu_count


def launcher_workers(argv: list[str], launcher: str, hydra_keys: dict, jobs: int | None, most: int | None):
    """The workers riskplan gives the launcher, added to `argv`: joblib's n_jobs (--jobs, or one per core), SLURM's
    array parallelism (--jobs), never more than `most` (the jobs, or an optimiser's trials at once). Returns the
    workers and the index in argv of the n_jobs riskplan sized (None when the launcher's pool is not riskplan's to
    start: the user set other joblib settings, or n_jobs to what is not a count)."""
    limit = [most] if most else []
    if launcher == "joblib":
        workers = min([jobs or cpu_count(), *limit])  # more workers than jobs would idle
        given = hydra_keys.get(N_JOBS)
        if given is None:
            argv.append(f"{N_JOBS}={workers}")
            return workers, len(argv) - 1
        value = given.value()
        others = [key for key in hydra_keys if key.startswith("hydra.launcher.") and key != N_JOBS]
        if others or isinstance(value, bool) or not isinstance(value, int) or value < 1:
            return workers, None
        # n_jobs alone: the pool riskplan would start, of the user's size, so it is started as riskplan's is
        where = next(i for i, arg in enumerate(argv) if arg.split("=", 1)[0].lstrip("+~") == N_JOBS)
        argv[where] = f"{N_JOBS}={min([value, *limit])}"
        return min([value, *limit]), where
    if jobs is None:
        return None, None
    if launcher != "submitit_slurm":
        raise BadInput(
            "--jobs", f"applies to the joblib and submitit_slurm launchers, not to hydra/launcher={launcher}"
        )
    workers = min([jobs, *limit])
    argv.append(f"hydra.launcher.array_parallelism={workers}")
    return workers, None


N_JOBS = "hydra.launcher.n_jobs"  # joblib's workers
RAY_INIT = "hydra.launcher.ray.init."
# what ray.init refuses when it connects to an existing cluster (the nodes were sized by `ray start` on each node)
RAY_CONNECT_REFUSES = (
    "num_cpus",
    "num_gpus",
    "resources",
    "labels",
    "object_store_memory",
    "_system_config",
    "_enable_object_reconstruction",
    "_node_name",
)


def ray_connects(launcher: str, hydra_keys: dict) -> bool:
    """Whether a Ray launcher connects to an existing cluster (init.address set: auto or host:port) rather than
    starting a Ray instance of its own."""
    address = hydra_keys.get(RAY_INIT + "address")
    if address is not None and not address.is_delete():
        return address.value() is not None
    return launcher == "ray_cluster"


def runs_here(launcher: str, hydra_keys: dict) -> bool:
    """Whether the launcher's jobs run on this machine below the driver, and so end with it (driver_watch)."""
    return launcher in LOCAL or (launcher == "ray" and not ray_connects(launcher, hydra_keys))


def ray_init_overrides(launcher: str, hydra_keys: dict) -> list[str]:
    """Only the ray.init arguments that fit the case. hydra-ray-launcher 1.2 adds object_store_memory (75 MiB)
    before ray.init(**init): right for a local instance, refused by ray.init when it connects to an existing
    cluster (init.address set: auto or host:port). There riskplan sets it to null (the nodes keep the object store
    `ray start` gave them) and refuses, as bad input, the other arguments ray.init would refuse."""
    if launcher not in ("ray", "ray_cluster"):
        return []
    check_extra("hydra/launcher", launcher)  # Hydra's Ray launcher, an extra of its own

    def given(key: str):
        override = hydra_keys.get(RAY_INIT + key)
        return override if override is not None and not override.is_delete() else None

    check_ray(launcher, hydra_keys)
    if not ray_connects(launcher, hydra_keys):
        # hydra/launcher=ray's own instance: ray.init(address=None) would join RAY_ADDRESS's cluster, or the one the
        # last `ray start` here recorded, and then refuse the object-store size; `local` always starts one
        return [f"++{RAY_INIT}address=local"] if launcher == "ray" else []
    for key in RAY_CONNECT_REFUSES:
        override = given(key)
        if override is not None and override.value() is not None:
            raise BadInput(
                f"override '{override.input_line}'",
                "ray.init does not take it when it connects to an existing Ray cluster (hydra.launcher.ray.init."
                "address is set): `ray start` sizes each node; CPUs per job: +hydra.launcher.ray.remote.num_cpus=N",
            )
    return ["++hydra.launcher.ray.init.object_store_memory=null"] if launcher == "ray" else []


RAY_REMOTE = "hydra.launcher.ray.remote"
CONNECT_SECONDS = 5.0  # a Ray head answers a TCP connection at once; an address that does not is a mistake
PROC = "/proc"  # the process table where Ray looks for a raylet (auto)
# ray.remote's options for a task (ray._common.ray_option_utils.task_options of Ray 2.60; Ray is not imported here)
RAY_TASK_OPTIONS = (
    "accelerator_type", "memory", "name", "num_cpus", "num_gpus", "object_store_memory", "placement_group",
    "placement_group_bundle_index", "placement_group_capture_child_tasks", "resources", "runtime_env",
    "scheduling_strategy", "enable_task_events", "label_selector", "fallback_strategy", "_labels", "max_calls",
    "max_retries", "num_returns", "retry_exceptions", "_generator_backpressure_num_objects",
    "_num_objects_per_yield", "concurrency_groups", "enable_tensor_transport",
)  # fmt: skip


def check_ray(
    launcher: str, hydra_keys: dict, environ=os.environ, timeout: float = CONNECT_SECONDS, proc: str = PROC
) -> None:
    """What Ray would refuse, or wait on forever, once the sweep had begun: ray.remote options it does not know
    (or values it rejects), an address that is not host:port, an address where nothing answers (ray.init retried
    it for ever, printing warnings, with the sweep directory written), and `auto` where it finds no Ray instance
    (ray.init's ConnectionError, with the sweep directory written). `environ` and `proc` are where Ray looks."""
    check_ray_remote(hydra_keys)
    address, key = ray_address(launcher, hydra_keys, environ)
    found = ""
    if address == "auto":
        address, found = auto_address(key, ray_temp_dir(hydra_keys, environ), proc)
    if address is None:
        if launcher == "ray":
            check_own_cpus(hydra_keys)
        return
    host, port = parse_ray_address(address, key)
    try:
        socket.create_connection((host, port), timeout=timeout).close()
    except OSError as err:
        why = "no answer" if isinstance(err, socket.timeout) else (err.strerror or str(err) or type(err).__name__)
        raise BadInput(
            key,
            f"no Ray cluster answers at {address} ({why}{found}); start one there (ray start --head --port={port}) "
            f"or give the address of the head node's `ray start`",
        ) from None


def check_own_cpus(hydra_keys: dict, machine: int | None = None) -> None:
    """A job asking the sweep's own Ray instance for more CPUs than it has (hydra.launcher.ray.init.num_cpus, else
    the machine's, `machine`) would wait for ever, Ray warning that it cannot be scheduled."""
    asked, has = given_value(hydra_keys, RAY_REMOTE, "num_cpus"), given_value(hydra_keys, RAY_INIT[:-1], "num_cpus")
    cpus = has if isinstance(has, (int, float)) and not isinstance(has, bool) else machine or os.cpu_count() or 1
    if isinstance(asked, (int, float)) and not isinstance(asked, bool) and asked > cpus:
        source = f"{RAY_INIT}num_cpus" if cpus == has else "this machine's"
        raise BadInput(
            f"{RAY_REMOTE}.num_cpus",
            f"got {asked:g}; the sweep's own Ray instance has {cpus:g} CPU{'s' if cpus != 1 else ''} ({source}), and "
            f"a job asking for more would wait for ever: give at most {cpus:g}",
        )


def given_value(hydra_keys: dict, node: str, name: str):
    """The value the command line gives `node`.`name`, as a dotted key or inside `node`'s mapping; None if neither."""
    override = hydra_keys.get(f"{node}.{name}")
    if override is None:
        override = hydra_keys.get(node)
        value = override.value() if override is not None and not override.is_delete() else None
        return value.get(name) if isinstance(value, dict) else None
    return None if override.is_delete() else override.value()


def ray_address(launcher: str, hydra_keys: dict, environ=os.environ) -> tuple[str | None, str]:
    """The address ray.init will connect to and the key it comes from: init.address, else (unset, null or auto)
    RAY_ADDRESS, as ray.init reads it; "auto" when Ray is to look for one on this machine (auto_address). None for
    a Ray instance of the sweep's own (local, or hydra/launcher=ray's unset or null address, made local)."""
    key = RAY_INIT + "address"
    override = hydra_keys.get(key)
    given = override is not None and not override.is_delete()
    value = override.value() if given else ("auto" if launcher == "ray_cluster" else None)
    if value is None and launcher == "ray":  # its own instance (ray_init_overrides: address=local)
        return None, key
    if value is None or value == "auto":
        if environ.get("RAY_ADDRESS"):
            value, key = environ["RAY_ADDRESS"], "RAY_ADDRESS"
    if value is None or value == "local":
        return None, key
    return str(value), key


def auto_address(key: str, temp_dir: str, proc: str) -> tuple[str | None, str]:
    """The address ray.init(address="auto") takes on this machine, found as Ray finds it (ray._private.services.
    get_ray_address_from_environment), and a note of where: the one the last `ray start` here wrote to
    <temp_dir>/ray_current_cluster, else the GCS address of a raylet running here. None where the processes cannot
    be listed (no /proc): Ray may still find one there. Bad input when there is neither."""
    current = os.path.join(temp_dir, "ray_current_cluster")
    try:
        with open(current) as recorded:
            return recorded.read().strip(), f"; auto read it from {current}"
    except OSError:  # no `ray start` recorded here (`ray stop` removes the file)
        pass
    raylets = raylet_addresses(proc)
    if raylets is None:
        return None, ""
    if raylets:
        return raylets[0], "; auto took it from a running raylet's --gcs-address"
    raise BadInput(
        key,
        f"auto found no running Ray instance on this machine (no {current}, no raylet process); start one "
        f"(ray start --head) or give HOST:PORT of a cluster's head (or RAY_ADDRESS)",
    )


def ray_temp_dir(hydra_keys: dict, environ=os.environ) -> str:
    """Where `ray start` records the cluster it started: ray.init's _temp_dir, else Ray's default (ray._common.
    utils.get_default_ray_temp_dir: RAY_TMPDIR, else TMPDIR on Linux, else /tmp, then ray/)."""
    given = hydra_keys.get(RAY_INIT + "_temp_dir")
    if given is not None and not given.is_delete() and given.value() is not None:
        return str(given.value())
    if "RAY_TMPDIR" in environ:
        base = environ["RAY_TMPDIR"]
    elif sys.platform.startswith("linux") and "TMPDIR" in environ:
        base = environ["TMPDIR"]
    else:
        base = "/tmp" if sys.platform.startswith(("linux", "darwin")) else tempfile.gettempdir()
    return os.path.join(base, "ray")


def raylet_addresses(proc: str = PROC) -> list[str] | None:
    """The --gcs-address of every raylet running on this machine, sorted, from <proc>/PID/cmdline as Ray reads the
    command lines (services._find_address_from_flag, through psutil, which this environment may lack); None
    without a process table to read."""
    try:
        pids = [name for name in os.listdir(proc) if name.isdigit()]
    except OSError:
        return None
    found = set()
    for pid in pids:
        try:
            with open(os.path.join(proc, pid, "cmdline"), "rb") as cmdline:
                args = cmdline.read().decode(errors="replace").rstrip("\0").split("\0")
        except OSError:  # ended since, or not ours to read
            continue
        if len(args) == 1:
            args = args[0].split(" ")  # a process that rewrote its title, as psutil splits it
        if "raylet" not in os.path.basename(args[0]):
            continue
        for arg in " ".join(args).split(" "):
            flag, _, value = arg.partition("=")
            if flag == "--gcs-address" and value not in ("", "None"):
                found.add(value)
    return sorted(found)


def parse_ray_address(address: str, key: str) -> tuple[str, int]:
    """(host, port) of host:port, [ipv6]:port or ray://host:port; bad input otherwise (ray.init's 'Invalid address
    format')."""
    match = re.fullmatch(r"(?:ray://)?(?:\[([0-9A-Fa-f:.]+)\]|([^\s:/\[\]]+)):(\d{1,5})", address)
    port = int(match.group(3)) if match else 0
    if not match or not 0 < port < 65536:
        raise BadInput(
            key,
            f"got {address!r}; expected HOST:PORT of a Ray cluster's head (e.g. 10.0.0.1:6379), ray://HOST:PORT, "
            f"auto or local",
        )
    return match.group(1) or match.group(2), port


def check_ray_remote(hydra_keys: dict) -> None:
    """hydra.launcher.ray.remote's options as ray.remote judges them (RAY_TASK_OPTIONS' names, RAY_COUNTS'
    numbers, `resources`' quantities): what it refuses is bad input, not a ValueError from the launcher once the
    sweep is written. Ray itself is not imported here: imported in the driver before the launcher's ray.init, it
    keeps that call's lines out of sweep.log (the options not listed in RAY_COUNTS are Ray's to check)."""
    for key, override in hydra_keys.items():
        if override.is_delete() or not (key == RAY_REMOTE or key.startswith(RAY_REMOTE + ".")):
            continue
        if key == RAY_REMOTE:
            value = override.value()
            given = [(str(k), [], v) for k, v in value.items()] if isinstance(value, dict) else []
        else:  # deeper keys (resources.GPU=1): an option's part
            name, *inside = key[len(RAY_REMOTE) + 1 :].split(".")
            given = [(name, inside, override.value())]
        for name, inside, value in given:
            where = ".".join([RAY_REMOTE, name, *inside])
            if name not in RAY_TASK_OPTIONS:
                raise BadInput(
                    where, f"ray.remote has no option '{name}'; valid options: {', '.join(sorted(RAY_TASK_OPTIONS))}"
                )
            problem = _ray_option_problem(name, inside, value)
            if problem:
                raise BadInput(where, f"got {value!r}; ray.remote takes {problem}")


# ray.remote's numbers as Ray 2.60 checks them (ray._common.ray_option_utils): the least each takes, and whether it
# may be a fraction (a resource: 0 or at least Ray's unit, 0.0001)
RAY_COUNTS = {
    "num_cpus": (0, True), "num_gpus": (0, True), "memory": (0, True),
    "object_store_memory": (0, False), "max_calls": (0, False), "max_retries": (-1, False),
}  # fmt: skip
RAY_UNIT = 1e-4


def _ray_option_problem(name: str, inside: list[str], value) -> str:
    """What ray.remote would refuse in option `name` (`inside`: the part of it a dotted key set), as the values it
    takes, or ''."""
    if name == "resources":
        quantities = {inside[0]: value} if inside else value
        if not isinstance(quantities, dict):
            return "a mapping of resource names to quantities"
        if "CPU" in quantities or "GPU" in quantities:
            return "CPUs and GPUs as num_cpus and num_gpus, not among resources"
        return next(filter(None, (_count_problem(q, 0, True) for q in quantities.values())), "")
    if name in RAY_COUNTS and not inside:
        return _count_problem(value, *RAY_COUNTS[name])
    return ""


def _count_problem(value, least: int, fraction: bool) -> str:
    """Why ray.remote refuses a quantity (None passes: Ray's default), or ''."""
    if value is None:
        return ""
    if fraction:
        ok = isinstance(value, (int, float)) and math.isfinite(value) and (value == 0 or value >= RAY_UNIT)
        return "" if ok else f"0, a number of at least {RAY_UNIT:g}, or null"
    return "" if isinstance(value, int) and value >= least else f"a whole number of at least {least}, or null"
