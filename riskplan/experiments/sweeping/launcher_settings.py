"""The launcher's settings riskplan adds to a sweep's command line: its workers (joblib's n_jobs, SLURM's array
parallelism), and the ray.init arguments that fit a local Ray instance or a connection to a cluster."""

from __future__ import annotations

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

    if not ray_connects(launcher, hydra_keys):
        return []
    for key in RAY_CONNECT_REFUSES:
        override = given(key)
        if override is not None and override.value() is not None:
            raise BadInput(
                f"override '{override.input_line}'",
                "ray.init does not take it when it connects to an existing Ray cluster (hydra.launcher.ray.init."
                "address is set): `ray start` sizes each node; CPUs per job: +hydra.launcher.ray.remote.num_cpus=N",
            )
    return ["++hydra.launcher.ray.init.object_store_memory=null"] if launcher == "ray" else []
