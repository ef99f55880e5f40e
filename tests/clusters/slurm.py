"""A real one-node SLURM cluster that a test starts and stops itself.

    with SlurmCluster() as cluster:                  # or cluster = SlurmCluster().start() ... cluster.stop()
        job = cluster.submit("--wrap", "hostname")   # sbatch --parsable ...
        assert cluster.wait_for(job) == "COMPLETED"
        subprocess.run(["riskplan", "sweep", ...], env=cluster.env)   # any SLURM client, with cluster.env

What it runs, all from Debian's packages (bookworm: Slurm 22.05, MUNGE 0.5, MariaDB 10.11), each as a child
process of this one, in the foreground, with its pid recorded:

    munged      its own key, socket, pid, log and seed files in the cluster's temporary directory
    mariadbd    a throwaway database in the temporary directory, listening on 127.0.0.1 only      } accounting
    slurmdbd    the accounting daemon, so that `sacct` answers (submitit polls job states with it) } (default on)
    slurmctld   the controller, SlurmUser=root
    slurmd      the one node, named after `hostname -s`, with the CPUs and memory `slurmd -C` reports

Why accounting: submitit (hydra-submitit-launcher) learns a job's state only from `sacct -o JobID,State,NodeList
--parsable2 -j ...` (submitit/slurm/slurm.py, SlurmInfoWatcher), never squeue or scontrol. Without accounting
sacct exits 1 ("Slurm accounting storage is disabled", printed on the user's terminal at every poll); submitit
logs "Bypassing sacct error" and keeps the state UNKNOWN, which counts as not finished. A job that writes its
result pickle still completes the sweep, but one that ends without it (scancel, a node failure, a time limit) is
waited for forever: measured here, `riskplan sweep` was still waiting 2 minutes after an scancel. A lighter way
does not exist in 22.05: jobcomp/filetxt is read by `sacct -c` only, which submitit does not pass, and slurmdbd
stores into MySQL/MariaDB only. So slurmdbd + a throwaway MariaDB it is (about 0.5 s of start-up on an idle
machine; Debian's slurmdbd and mariadb-server-core).

Every daemon gets a free port of its own on 127.0.0.1 and every file lives in one temporary directory, so the
cluster neither needs nor touches /etc/slurm, /etc/munge, /run/munge, a system munged/slurmd/MariaDB, or the
default ports, and two clusters can run side by side. Clients find it through `SLURM_CONF` (in `cluster.env`);
slurm.conf's `AuthInfo=socket=...` points them (and the daemons) at this cluster's munged, and
`AccountingStoragePass=<socket>` does the same for the connections to slurmdbd, which do not read AuthInfo.

Stopping cancels the cluster's jobs, then ends exactly the pids it started (SIGTERM, SIGKILL after a grace
period) and waits for them. Job processes are not the daemons' children (slurmstepd detaches), so after the
daemons are gone any process whose environment holds this cluster's unique SLURM_CONF path (slurmstepd, a job,
a client a test left running) is killed by pid too; `cluster.leftovers` lists them. Nothing is stopped by name,
and no system service is touched. The daemons also get PR_SET_PDEATHSIG, so they die with the process that
started them even if it is killed without cleaning up (start the cluster from the main thread).

Settings that matter here (a container without a cgroup hierarchy Slurm can use, running as root):
    ProctrackType=proctrack/linuxproc   no cgroups; tracks job processes through /proc
    TaskPlugin=task/affinity            binds each job to its CPUs (sched_setaffinity works without cgroups);
                                        task/none works too, but then a job sees every CPU of the node
    JobAcctGatherType=jobacct_gather/none, SwitchType=switch/none, MpiDefault=none
    SelectType=select/cons_tres, SelectTypeParameters=CR_Core   CPUs are consumable, memory is not
    AuthInfo=...,cred_expire=5          a requeued job waits cred_expire seconds (default 120) before it may start
    SchedulerParameters=sched_interval=1,bf_interval=1   pending jobs (a requeued one) are looked at every second
    KillWait=5                          scancel: SIGTERM, then SIGKILL 5 s later (default 30)

Exceptions: ClusterUnavailable when this machine cannot run a cluster at all (not Linux, not root, SLURM not
installed and no way to install it): tests skip with its message. ClusterError when a daemon failed or the node
never came up: tests fail, and the message holds the tails of the daemons' logs.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import re
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

# Debian packages: the cluster itself, and the accounting (slurmdbd, which brings its MySQL plugin, and MariaDB's
# server alone: mariadbd and the SQL of its system tables).
PACKAGES = ("slurmctld", "slurmd", "slurm-client", "munge")
ACCOUNTING_PACKAGES = ("slurmdbd", "mariadb-server-core")
BINARIES = ("munged", "slurmctld", "slurmd", "sbatch", "squeue", "sinfo", "scontrol", "scancel", "sacct")
ACCOUNTING_BINARIES = ("slurmdbd", "mariadbd")
MARIADB_SQL = "/usr/share/mysql"  # mariadb-server-core's SQL for the system tables
SYSTEM_TABLES = ("mysql_system_tables.sql", "mysql_performance_tables.sql", "mysql_system_tables_data.sql")
SBIN = ("/usr/sbin", "/sbin", "/usr/bin", "/bin", "/usr/local/sbin", "/usr/local/bin")

PARTITION = "debug"
FINISHED = frozenset(
    {
        "COMPLETED",
        "FAILED",
        "CANCELLED",
        "TIMEOUT",
        "OUT_OF_MEMORY",
        "NODE_FAIL",
        "PREEMPTED",
        "BOOT_FAIL",
        "DEADLINE",
        "REVOKED",
    }
)
CLIENT_ENV_PREFIXES = ("SLURM_", "SBATCH_", "SALLOC_", "SRUN_", "SQUEUE_", "SINFO_", "SACCT_", "SCONTROL_")


class ClusterUnavailable(RuntimeError):
    """This machine cannot run the cluster (tests skip with this message)."""


class ClusterError(RuntimeError):
    """The cluster was set up but did not come up or misbehaved (tests fail with this message)."""


def which(name: str) -> str | None:
    """`name` on PATH or in the sbin directories (a non-login root shell may lack /usr/sbin on PATH)."""
    return shutil.which(name) or shutil.which(name, path=os.pathsep.join(SBIN))


def missing_binaries(accounting: bool = True) -> list[str]:
    """The programs (and, for accounting, MariaDB's system-table SQL) that are not installed."""
    missing = [name for name in BINARIES + (ACCOUNTING_BINARIES if accounting else ()) if which(name) is None]
    if accounting:
        missing += [name for name in SYSTEM_TABLES if not (Path(MARIADB_SQL) / name).is_file()]
    return missing


def ensure_installed(accounting: bool = True, log=print) -> float:
    """Install the Debian packages when a binary is missing; return the seconds spent (0.0 when nothing was).

    Raises ClusterUnavailable when it cannot: not root, no apt-get, or the install fails (after one
    `apt-get update` and a retry)."""
    missing = missing_binaries(accounting)
    if not missing:
        return 0.0
    packages = PACKAGES + (ACCOUNTING_PACKAGES if accounting else ())
    if os.geteuid() != 0:
        raise ClusterUnavailable(
            f"SLURM is not installed ({', '.join(missing)} missing) and installing it "
            f"(apt-get install {' '.join(packages)}) needs root"
        )
    apt = shutil.which("apt-get")
    if apt is None:
        raise ClusterUnavailable(
            f"SLURM is not installed ({', '.join(missing)} missing) and there is no "
            f"apt-get to install {' '.join(packages)}"
        )
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    install = [apt, "install", "-y", "-q", "--no-install-recommends", "-o", "DPkg::Lock::Timeout=300", *packages]
    started = time.monotonic()
    log(f"installing {' '.join(packages)} (missing: {', '.join(missing)})")
    result = subprocess.run(install, env=env, capture_output=True, text=True, timeout=900)
    if result.returncode != 0:  # stale or absent package lists: update once and retry
        subprocess.run(
            [apt, "update", "-q", "-o", "DPkg::Lock::Timeout=300"], env=env, capture_output=True, text=True, timeout=600
        )
        result = subprocess.run(install, env=env, capture_output=True, text=True, timeout=900)
    if result.returncode != 0:
        tail = "\n".join((result.stdout + result.stderr).strip().splitlines()[-15:])
        raise ClusterUnavailable(f"apt-get install {' '.join(packages)} failed (exit {result.returncode}):\n{tail}")
    still = missing_binaries(accounting)
    if still:
        raise ClusterUnavailable(f"installed {' '.join(packages)} but {', '.join(still)} still missing")
    return time.monotonic() - started


def free_ports(count: int) -> list[int]:
    """`count` distinct TCP ports free on 127.0.0.1 right now (held open together so they differ)."""
    with contextlib.ExitStack() as stack:
        ports = []
        for _ in range(count):
            sock = stack.enter_context(socket.socket(socket.AF_INET, socket.SOCK_STREAM))
            sock.bind(("127.0.0.1", 0))
            ports.append(sock.getsockname()[1])
        return ports


def port_open(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.settimeout(0.2)
        return sock.connect_ex(("127.0.0.1", port)) == 0


def _die_with_parent() -> None:  # preexec_fn: the daemon gets SIGTERM when the thread that started it dies
    with contextlib.suppress(Exception):
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG


def _tail(path: Path, lines: int = 25) -> str:
    try:
        text = path.read_text(errors="replace").rstrip().splitlines()
    except OSError:
        return "(none)"
    return "\n".join(text[-lines:]) or "(empty)"


@dataclass
class Daemon:
    name: str
    process: subprocess.Popen
    logs: tuple[Path, ...]

    @property
    def pid(self) -> int:
        return self.process.pid


@dataclass
class SlurmCluster:
    """A one-node SLURM cluster (and its munged, and for accounting its slurmdbd and MariaDB) in a temp dir.

    accounting: run slurmdbd + MariaDB so that `sacct` works (submitit needs it to see a cancelled or failed job;
        without it such a job stays UNKNOWN and submitit waits forever). False starts only munged, slurmctld
        and slurmd (about 1 s to start instead of about 1.6 s; no MariaDB install).
    task_plugin: "task/affinity" (each job bound to its CPUs) or "task/none".
    install: apt-get install the packages when missing (else ClusterUnavailable when they are).
    keep: leave the temporary directory behind on stop (for debugging).
    """

    accounting: bool = True
    task_plugin: str = "task/affinity"
    cred_expire: int = 5
    kill_wait: int = 5
    start_timeout: float = 60.0
    install: bool = True
    keep: bool = False
    parent_dir: str | None = None
    log: object = print

    root: Path | None = field(default=None, init=False)
    conf: Path | None = field(default=None, init=False)
    node: str = field(default="", init=False)
    daemons: list[Daemon] = field(default_factory=list, init=False)
    timings: dict[str, float] = field(default_factory=dict, init=False)
    leftovers: list[str] = field(default_factory=list, init=False)
    env: dict[str, str] = field(default_factory=dict, init=False)

    # ------------------------------------------------------------------ start
    def start(self) -> SlurmCluster:
        if not sys.platform.startswith("linux"):
            raise ClusterUnavailable(f"a SLURM cluster needs Linux, not {sys.platform}")
        if os.geteuid() != 0:
            raise ClusterUnavailable(
                "starting a SLURM cluster needs root (slurmd runs jobs as their user; "
                "this cluster runs with SlurmUser=root)"
            )
        if self.install:
            self.timings["install"] = ensure_installed(self.accounting, log=self.log)
        elif missing_binaries(self.accounting):
            raise ClusterUnavailable(f"SLURM is not installed: {', '.join(missing_binaries(self.accounting))} missing")
        started = time.monotonic()
        try:
            self._start()
        except BaseException:
            self.stop()
            raise
        self.timings["start"] = time.monotonic() - started
        return self

    def _start(self) -> None:
        self.root = Path(tempfile.mkdtemp(prefix="riskplan-slurm-", dir=self.parent_dir))
        os.chmod(self.root, 0o755)  # munged wants every directory above its socket searchable by all
        for sub in ("munge", "state", "spool", "log", "db"):
            (self.root / sub).mkdir(mode=0o755)
        self.conf = self.root / "slurm.conf"
        self.node = socket.gethostname().split(".")[0] or "localhost"
        ctld_port, slurmd_port, dbd_port, db_port = free_ports(4)
        munge_socket = self.root / "munge" / "munge.socket"
        self.env = self._client_env()

        key = self.root / "munge" / "munge.key"
        key.write_bytes(secrets.token_bytes(128))
        key.chmod(0o600)
        self._spawn(
            "munged",
            [
                which("munged"),
                "--foreground",
                "--num-threads=10",
                f"--socket={munge_socket}",
                f"--pid-file={self.root / 'munge' / 'munged.pid'}",
                f"--log-file={self.root / 'log' / 'munged.log'}",
                f"--key-file={key}",
                f"--seed-file={self.root / 'munge' / 'munged.seed'}",
            ],
        )
        if self.accounting:  # the database's files while munged starts
            self._init_database()
        self._wait("munged's socket", munge_socket.exists)

        if self.accounting:
            self._start_database(db_port)
            self._start_slurmdbd(dbd_port, db_port, munge_socket)

        self.conf.write_text(self._slurm_conf(ctld_port, slurmd_port, dbd_port, munge_socket))
        self._spawn("slurmctld", [which("slurmctld"), "-D", "-i"], extra_logs=("slurmctld.log",))
        self._spawn("slurmd", [which("slurmd"), "-D", "-N", self.node], extra_logs=("slurmd.log",))
        self._wait(f"node {self.node} idle in sinfo", self._node_idle)

    def _client_env(self) -> dict[str, str]:
        """This process's environment without another cluster's SLURM_* settings, plus SLURM_CONF."""
        env = {k: v for k, v in os.environ.items() if not k.startswith(CLIENT_ENV_PREFIXES)}
        env["SLURM_CONF"] = str(self.conf)
        return env

    def _slurm_conf(self, ctld_port: int, slurmd_port: int, dbd_port: int, munge_socket: Path) -> str:
        r = self.root
        accounting = (
            [
                "AccountingStorageType=accounting_storage/slurmdbd",
                "AccountingStorageHost=127.0.0.1",
                f"AccountingStoragePort={dbd_port}",
                f"AccountingStoragePass={munge_socket}",  # the munge socket for slurmdbd connections
            ]
            if self.accounting
            else ["AccountingStorageType=accounting_storage/none"]
        )
        return "\n".join(
            [
                "# written by tests/clusters/slurm.py: a throwaway one-node cluster",
                "ClusterName=riskplan",
                f"SlurmctldHost={self.node}(127.0.0.1)",
                f"SlurmctldPort={ctld_port}",
                f"SlurmdPort={slurmd_port}",
                "SlurmUser=root",
                "SlurmdUser=root",
                "AuthType=auth/munge",
                "CredType=cred/munge",
                f"AuthInfo=socket={munge_socket},cred_expire={self.cred_expire}",
                f"StateSaveLocation={r / 'state'}",
                f"SlurmdSpoolDir={r / 'spool'}",
                f"SlurmctldPidFile={r / 'slurmctld.pid'}",
                f"SlurmdPidFile={r / 'slurmd.pid'}",
                f"SlurmctldLogFile={r / 'log' / 'slurmctld.log'}",
                f"SlurmdLogFile={r / 'log' / 'slurmd.log'}",
                "SlurmctldDebug=info",
                "SlurmdDebug=info",
                f"PlugStackConfig={r / 'plugstack.conf'}",  # none: not /etc/slurm's
                "ProctrackType=proctrack/linuxproc",
                f"TaskPlugin={self.task_plugin}",
                "JobAcctGatherType=jobacct_gather/none",
                "SwitchType=switch/none",
                "MpiDefault=none",
                "SelectType=select/cons_tres",
                "SelectTypeParameters=CR_Core",
                "SchedulerType=sched/backfill",
                "SchedulerParameters=sched_interval=1,bf_interval=1",
                "ReturnToService=2",
                f"KillWait={self.kill_wait}",
                "MinJobAge=300",
                "MailProg=/bin/true",
                "JobCompType=jobcomp/none",
                *accounting,
                f"NodeName={self.node} NodeAddr=127.0.0.1 {self._hardware()} State=UNKNOWN",
                f"PartitionName={PARTITION} Nodes={self.node} Default=YES MaxTime=INFINITE State=UP",
                "",
            ]
        )

    def _hardware(self) -> str:
        """The node's CPUs, sockets, cores, threads and memory as `slurmd -C` sees them (slurmd drains a node
        configured with more than it finds)."""
        try:
            out = subprocess.run([which("slurmd"), "-C"], capture_output=True, text=True, timeout=30).stdout
            line = next(line for line in out.splitlines() if line.startswith("NodeName="))
            return " ".join(word for word in line.split() if not word.startswith("NodeName="))
        except (OSError, subprocess.SubprocessError, StopIteration):
            mem_kib = int(re.search(r"MemTotal:\s+(\d+)", Path("/proc/meminfo").read_text()).group(1))
            return f"CPUs={os.cpu_count()} RealMemory={mem_kib // 1024 - 256}"

    def _init_database(self) -> None:
        """MariaDB's system tables, by `mariadbd --bootstrap` as mariadb-install-db does, less its help tables,
        GIS procedures and sys schema (which slurmdbd does not use): ~0.3 s on an idle machine instead of ~1-3 s."""
        data = self.root / "db" / "data"
        data.mkdir()
        sql = "create database if not exists mysql;\nuse mysql;\nSET @auth_root_socket='root';\n" + "".join(
            (Path(MARIADB_SQL) / name).read_text() for name in SYSTEM_TABLES
        )
        result = subprocess.run(
            [
                which("mariadbd"),
                "--no-defaults",
                "--bootstrap",
                f"--datadir={data}",
                "--user=root",
                "--log-warnings=0",
                "--enforce-storage-engine=",
                "--max_allowed_packet=8M",
                "--net_buffer_length=16K",
                *self._db_sizes(),
            ],
            input=sql,
            capture_output=True,
            text=True,
            timeout=120,
            cwd=self.root,
        )
        if result.returncode != 0:
            raise ClusterError(
                f"mariadbd --bootstrap failed (exit {result.returncode}):\n"
                + "\n".join((result.stdout + result.stderr).splitlines()[-20:])
            )

    @staticmethod
    def _db_sizes() -> list[str]:
        return ["--innodb-log-file-size=8M", "--innodb-buffer-pool-size=32M"]  # ~30 MB on disk, not ~115

    def _start_database(self, port: int) -> None:
        db = self.root / "db"
        self._db_password = secrets.token_hex(12)
        init = db / "init.sql"
        init.write_text(
            f"CREATE USER IF NOT EXISTS 'slurm'@'127.0.0.1' IDENTIFIED BY '{self._db_password}';\n"
            "GRANT ALL PRIVILEGES ON *.* TO 'slurm'@'127.0.0.1';\n"
        )
        init.chmod(0o600)
        error_log = db / "error.log"
        self._spawn(
            "mariadbd",
            [
                which("mariadbd"),
                "--no-defaults",
                f"--datadir={db / 'data'}",
                "--user=root",
                "--bind-address=127.0.0.1",
                f"--port={port}",
                f"--socket={db / 'mysqld.sock'}",
                f"--pid-file={db / 'mysqld.pid'}",
                f"--log-error={error_log}",
                "--skip-name-resolve",
                f"--init-file={init}",
                "--innodb-lock-wait-timeout=900",
                *self._db_sizes(),
            ],
            extra_logs=(error_log,),
        )
        self._wait("MariaDB ready", lambda: "ready for connections" in _read(error_log) and port_open(port))

    def _start_slurmdbd(self, dbd_port: int, db_port: int, munge_socket: Path) -> None:
        # slurmdbd reads slurmdbd.conf from SLURM_CONF's directory (it has no option for it); mode 600 required
        dbd_conf = self.root / "slurmdbd.conf"
        dbd_conf.write_text(
            "\n".join(
                [
                    "AuthType=auth/munge",
                    f"AuthInfo=socket={munge_socket}",
                    "DbdHost=localhost",
                    "DbdAddr=127.0.0.1",
                    f"DbdPort={dbd_port}",
                    "SlurmUser=root",
                    "DebugLevel=info",
                    f"LogFile={self.root / 'log' / 'slurmdbd.log'}",
                    f"PidFile={self.root / 'slurmdbd.pid'}",
                    "StorageType=accounting_storage/mysql",
                    "StorageHost=127.0.0.1",
                    f"StoragePort={db_port}",
                    "StorageUser=slurm",
                    f"StoragePass={self._db_password}",
                    "StorageLoc=slurm_acct_db",
                    "",
                ]
            )
        )
        dbd_conf.chmod(0o600)
        self._spawn("slurmdbd", [which("slurmdbd"), "-D"], extra_logs=("slurmdbd.log",))
        self._wait("slurmdbd listening", lambda: port_open(dbd_port))

    def _spawn(self, name: str, argv: list, extra_logs: tuple = ()) -> Daemon:
        out = self.root / "log" / f"{name}.out"
        logs = (out, *(p if isinstance(p, Path) else self.root / "log" / p for p in extra_logs))
        with open(out, "wb") as sink:
            process = subprocess.Popen(
                [str(a) for a in argv],
                stdin=subprocess.DEVNULL,
                stdout=sink,
                stderr=subprocess.STDOUT,
                env=self._daemon_env(),
                cwd=self.root,
                start_new_session=True,
                preexec_fn=_die_with_parent,
            )
        daemon = Daemon(name, process, logs)
        self.daemons.append(daemon)
        return daemon

    def _daemon_env(self) -> dict[str, str]:
        env = {k: v for k, v in self.env.items() if k in ("PATH", "LANG", "LC_ALL", "TZ", "HOME", "SLURM_CONF")}
        env["PATH"] = os.pathsep.join([env.get("PATH", ""), *SBIN])
        return env

    def _wait(self, what: str, ready, timeout: float | None = None) -> None:
        deadline = time.monotonic() + (timeout or self.start_timeout)
        while True:
            for daemon in self.daemons:
                if daemon.process.poll() is not None:
                    raise ClusterError(
                        f"{daemon.name} (pid {daemon.pid}) exited with {daemon.process.returncode} "
                        f"while waiting for {what}\n{self.logs()}"
                    )
            if ready():
                return
            if time.monotonic() > deadline:
                raise ClusterError(
                    f"timed out after {timeout or self.start_timeout:.0f} s waiting for {what}\n{self.logs()}"
                )
            time.sleep(0.1)

    def _node_idle(self) -> bool:
        result = self.run("sinfo", "-h", "-N", "-o", "%N %T", check=False, timeout=10)
        return result.returncode == 0 and f"{self.node} idle" in result.stdout.splitlines()

    # ------------------------------------------------------------------ use
    def run(self, *args: str, check: bool = True, timeout: float = 60) -> subprocess.CompletedProcess:
        """Run a SLURM client (sbatch, squeue, ...) against this cluster; raise ClusterError when it fails."""
        command = [which(args[0]) or args[0], *args[1:]]
        result = subprocess.run(command, env=self.env, capture_output=True, text=True, timeout=timeout)
        if check and result.returncode != 0:
            raise ClusterError(f"{' '.join(args)} exited {result.returncode}: {result.stderr.strip()}")
        return result

    def submit(self, *sbatch_args: str) -> str:
        """sbatch --parsable ...: the job id."""
        return self.run("sbatch", "--parsable", *sbatch_args).stdout.strip().split(";")[0]

    def queue(self) -> list[str]:
        """Ids of the jobs squeue lists (pending, running, completing)."""
        return self.run("squeue", "-h", "-o", "%i").stdout.split()

    def state(self, job: str) -> str:
        """The job's state: from sacct with accounting (what submitit sees), else from scontrol; "" if unknown."""
        if self.accounting:
            out = self.run("sacct", "-n", "-X", "-P", "-o", "State", "-j", job, check=False).stdout
            states = [line.split()[0] for line in out.splitlines() if line.strip()]
            return states[-1] if states else ""
        out = self.run("scontrol", "-o", "show", "job", job, check=False).stdout
        match = re.search(r"JobState=(\S+)", out)
        return match.group(1) if match else ""

    def wait_for(self, job: str, states=FINISHED, timeout: float = 120) -> str:
        """Wait until the job's state is one of `states` (default: any finished state); return it."""
        deadline = time.monotonic() + timeout
        while True:
            state = self.state(job)
            if state in states:
                return state
            if time.monotonic() > deadline:
                raise ClusterError(f"job {job} still {state or 'unknown'} after {timeout:.0f} s\n{self.logs()}")
            time.sleep(0.2)

    def logs(self, lines: int = 25) -> str:
        """The tails of every daemon's output and log files."""
        parts = []
        for daemon in self.daemons:
            for path in daemon.logs:
                if path.exists():
                    parts.append(f"--- {daemon.name} (pid {daemon.pid}): {path}\n{_tail(path, lines)}")
        return "\n".join(parts)

    # ------------------------------------------------------------------ stop
    def stop(self) -> None:
        """Cancel this cluster's jobs, end the pids it started and wait for them, remove the temporary dir."""
        if self.root is None:
            return
        ctld = next((d for d in self.daemons if d.name == "slurmctld" and d.process.poll() is None), None)
        if ctld is not None:
            with contextlib.suppress(Exception):
                jobs = self.queue()
                if jobs:
                    self.run("scancel", *jobs, check=False)
                    deadline = time.monotonic() + self.kill_wait + 10
                    while self.queue() and time.monotonic() < deadline:
                        time.sleep(0.2)
        for daemon in reversed(self.daemons):  # slurmd, slurmctld, slurmdbd, mariadbd, munged
            if daemon.process.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    daemon.process.send_signal(signal.SIGTERM)
                try:
                    daemon.process.wait(timeout=20)
                except subprocess.TimeoutExpired:
                    with contextlib.suppress(ProcessLookupError):
                        daemon.process.kill()
                    daemon.process.wait(timeout=10)
        self._kill_leftovers()
        if not self.keep:
            shutil.rmtree(self.root, ignore_errors=True)
        self.root = None

    def _kill_leftovers(self) -> None:
        """SIGKILL, by pid, the processes this cluster started that outlived the daemons: their environment
        holds this cluster's SLURM_CONF, a path under a directory made for this cluster alone."""
        marker = f"SLURM_CONF={self.conf}".encode()
        me = {os.getpid(), os.getppid()}
        for proc in Path("/proc").iterdir():
            if not proc.name.isdigit() or int(proc.name) in me:
                continue
            try:
                if marker not in (proc / "environ").read_bytes().split(b"\0"):
                    continue
                cmdline = (proc / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace").strip()
                os.kill(int(proc.name), signal.SIGKILL)
                self.leftovers.append(f"{proc.name} {cmdline}")
            except (OSError, ValueError):
                continue

    def pids(self) -> dict[str, int]:
        return {daemon.name: daemon.pid for daemon in self.daemons}

    def __enter__(self) -> SlurmCluster:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()


def _read(path: Path) -> str:
    try:
        return path.read_text(errors="replace")
    except OSError:
        return ""


if __name__ == "__main__":  # python tests/clusters/slurm.py: start one, show it, stop it
    with SlurmCluster() as demo:
        print(f"up in {demo.timings['start']:.1f} s (install {demo.timings.get('install', 0):.1f} s): {demo.pids()}")
        print(demo.run("sinfo").stdout)
        print(f"export SLURM_CONF={demo.conf}")
