"""A real multi-node Ray cluster on this machine that a test starts and stops itself (two nodes by default).

    with RayCluster() as cluster:                       # or cluster = RayCluster().start() ... cluster.stop()
        os.environ.update(cluster.driver_env)           # the token and RAY_ADDRESS (see below), before ray.init
        ray.init(address=cluster.address)               # a driver; ray.nodes() shows cluster.num_nodes alive nodes
        subprocess.run(["riskplan", "sweep", ..., "hydra/launcher=ray_cluster"],   # its address: auto
                       env={**os.environ, **cluster.driver_env})
        cluster.node_of_worker(pid)                     # the ip of the node whose Ray worker had this pid

    RayCluster(ray_executable="/other/venv/bin/ray")    # a cluster of another venv's Ray (the driver must use the
                                                        # same Ray version: the Hydra Ray launcher's venv)

What it runs: `ray start --head --block` and, for each further node, `ray start --address=HEAD --block`, each a
child process of this one in a process group (session) of its own, with PR_SET_PDEATHSIG so it ends with the
process that started it. `--block` keeps each `ray start` in the foreground as the parent of its node's daemons
(gcs_server, raylet, the agents, ...), which stay in its process group.

Each node has a loopback address of its own (head 127.0.0.2, then 127.0.0.3, ...; Linux routes all of
127.0.0.0/8 to lo). Ray replaces 127.0.0.1/localhost by the machine's routable address (ray._private.services.
resolve_ip_for_localhost), so `--node-ip-address=127.0.0.1` would put the cluster's traffic on the external
interface; 127.0.0.2 and up are not treated as "localhost" and are used as given. Distinct addresses also make
the nodes distinct to Ray (`node:<ip>` resources, NodeManagerAddress) and keep a driver from attaching to the
wrong raylet. Every port is chosen free and passed explicitly (GCS, dashboard, client server, node manager,
object manager, dashboard agent http/grpc, runtime-env agent, metrics), worker ports are left to the OS
(--min-worker-port=0 --max-worker-port=0), so nothing uses Ray's defaults (6379, 8265, 10001, 52365,
10002-19999) and two clusters, or a cluster and a local `ray.init()`, can run side by side.

Each node has its own --temp-dir under one short temporary directory (Unix socket paths must stay under 107
bytes, so it is in /tmp, not in pytest's long tmp_path). Per-node temp dirs need Ray >= 2.52 (ray-project/ray
PR #57735); older Ray ignores --temp-dir on a non-head node with a warning and uses the head's, which also works.

Ray >= 2.5x enables token authentication by default and, without a token, writes a new one to
~/.ray/auth_token. The cluster gets a random token through RAY_AUTH_MODE=token and RAY_AUTH_TOKEN instead (so it
writes nothing to ~/.ray), and a driver needs the same two variables: `cluster.driver_env` in a child's
environment, or `cluster.apply_driver_env()` in this process (Ray caches RAY_AUTH_MODE when it is imported, so
setting os.environ alone is not enough there). Ray versions without token auth ignore them.

`driver_env` also holds RAY_ADDRESS (the head's GCS address, once the cluster has started), which is what a user on
a node of the cluster has: `ray.init(address="auto")` (hydra/launcher=ray_cluster) takes RAY_ADDRESS first, then
the address `ray start` wrote to /tmp/ray/ray_current_cluster, then any Ray instance it finds running on the
machine. This cluster's nodes write that file into their own --temp-dir, never /tmp/ray, so without RAY_ADDRESS
`auto` would fall back to the last rule and could pick another Ray instance on the machine (seen here: another
test's local instance). The nodes themselves are started without RAY_ADDRESS. Usage stats are off (RAY_USAGE_STATS_ENABLED=0, --disable-usage-stats) and the SIGTERM
drain is skipped (RAY_GRACEFUL_SHUTDOWN_DRAIN_TIMEOUT_S=0; otherwise a node waits up to 30 s before stopping).

Stopping (non-head nodes first, then the head): SIGTERM to each `ray start` (it stops its node's daemons), a grace
period, then SIGKILL to its whole process group, then SIGKILL to any process still alive among the descendants
recorded just before stopping (matched by pid and start time, so a reused pid is never hit). Nothing is stopped
by name and `ray stop` is never run (it ends every Ray process on the machine). `cluster.leftovers` lists what
had to be killed after the grace period.

Only the ray CLI (core `ray`, no `ray[default]`) is needed: `--include-dashboard=false` still starts Ray's
minimal dashboard process and agents, which core Ray ships.

Skips (pytest.skip, or ClusterUnavailable outside pytest) when Ray is not importable / the ray executable does not
exist. ClusterError when a node fails or the nodes do not all show up alive within `timeout`; its message holds the
tails of the `ray start` outputs and of the nodes' gcs_server/raylet logs.

Run by hand (prints the address and the driver variables, stops on Enter or SIGTERM/SIGINT):
    python tests/clusters/ray_cluster.py [--ray /path/to/venv/bin/ray] [--nodes 2]
"""

from __future__ import annotations

import contextlib
import ctypes
import importlib.util
import json
import os
import random
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HEAD_IP = "127.0.0.2"  # the head; node i gets 127.0.0.(2 + i)
OBJECT_STORE_BYTES = 100 * 1000 * 1000  # Ray's minimum is 75 MiB (78643200 bytes)
_PR_SET_PDEATHSIG = 1
# the ports a non-head node needs, then the head's extra ones
_NODE_PORTS = (
    "node-manager-port",
    "object-manager-port",
    "dashboard-agent-listen-port",
    "dashboard-agent-grpc-port",
    "runtime-env-agent-port",
    "metrics-export-port",
)
_HEAD_PORTS = ("port", "dashboard-port", "ray-client-server-port")

# Run in the Ray venv's python: connect as a driver, wait until `want` nodes are alive, print them as JSON.
_PROBE = r"""
import json, sys, time
address, want, timeout = sys.argv[1], int(sys.argv[2]), float(sys.argv[3])
import ray
ray.init(address=address, logging_level="ERROR", log_to_driver=False)
deadline = time.monotonic() + timeout
while True:
    alive = [n for n in ray.nodes() if n["Alive"]]
    if len(alive) >= want or time.monotonic() > deadline:
        break
    time.sleep(0.2)
print(json.dumps({"ray": ray.__version__, "nodes": [
    {"id": n["NodeID"], "ip": n["NodeManagerAddress"], "resources": n["Resources"]} for n in alive]}))
ray.shutdown()
"""


class ClusterUnavailable(RuntimeError):
    """This machine or environment cannot run the cluster (tests skip)."""


class ClusterError(RuntimeError):
    """The cluster failed to start or to come up (tests fail); the message holds the logs' tails."""


def _unavailable(reason: str):
    if "pytest" not in sys.modules:  # used outside pytest (the command line below)
        raise ClusterUnavailable(reason)
    import pytest

    pytest.skip(reason)


def _refresh_ray_auth() -> None:
    """After RAY_AUTH_MODE/RAY_AUTH_TOKEN change in os.environ: Ray caches the mode in its config when it is imported
    and the token in its token loader once read, and a stale token makes the next local `ray.init` in this process
    fail ("InvalidAuthToken"), so both caches are refreshed (as ray._private.authentication does when it turns token
    auth on)."""
    if "ray" not in sys.modules:
        return
    with contextlib.suppress(ImportError, AttributeError):
        from ray._raylet import AuthenticationTokenLoader, Config

        Config.initialize("")
        AuthenticationTokenLoader.instance().reset_cache()


def _start_time(pid: int) -> int | None:
    """The process's start time in clock ticks (field 22 of /proc/PID/stat), None when it is gone."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return int(stat.rsplit(")", 1)[1].split()[19])


def _children_map() -> dict[int, list[int]]:
    children: dict[int, list[int]] = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            children.setdefault(ppid, []).append(int(entry.name))
    return children


def _descendants(roots: list[int]) -> dict[int, int]:
    """{pid: start time} of the roots and all their descendants."""
    children, found, todo = _children_map(), {}, list(roots)
    while todo:
        pid = todo.pop()
        start = _start_time(pid)
        if start is not None and pid not in found:
            found[pid] = start
            todo.extend(children.get(pid, []))
    return found


def _group_members(pgid: int) -> list[int]:
    members = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            except (OSError, IndexError):
                continue
            if int(fields[2]) == pgid and fields[0] != "Z":
                members.append(int(entry.name))
    return members


def _free_ports(count: int, host: str = "") -> list[int]:
    """`count` consecutive ports below the ephemeral range (32768-60999 on Linux), each free on every interface,
    so that no outgoing connection takes one of them before Ray binds it."""
    for _ in range(200):
        base = random.randrange(20000, 32000 - count)
        socks = []
        try:
            for port in range(base, base + count):
                s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
                socks.append(s)
                s.bind((host, port))
            return list(range(base, base + count))
        except OSError:
            continue
        finally:
            for s in socks:
                s.close()
    raise ClusterError(f"found no {count} free consecutive ports in 20000-32000")


def _python_of(ray_executable: Path) -> str:
    """The interpreter of a console script (its shebang), else the python beside it, else this one."""
    with contextlib.suppress(OSError, UnicodeDecodeError):
        first = ray_executable.read_bytes()[:400].split(b"\n", 1)[0].decode()
        if first.startswith("#!") and "python" in first:
            candidate = first[2:].strip().split()[0]
            if os.access(candidate, os.X_OK):
                return candidate
    beside = ray_executable.with_name("python")
    return str(beside) if os.access(beside, os.X_OK) else sys.executable


def _tail(path: Path, lines: int = 25) -> str:
    try:
        text = path.read_text(errors="replace").splitlines()
    except OSError:
        return "(missing)"
    return "\n".join(text[-lines:]) or "(empty)"


class _Node:
    def __init__(self, index: int, ip: str, ports: dict[str, int], temp_dir: Path, log: Path):
        self.index, self.ip, self.ports, self.temp_dir, self.log = index, ip, ports, temp_dir, log
        self.proc: subprocess.Popen | None = None

    @property
    def name(self) -> str:
        return "head" if self.index == 0 else f"node{self.index}"


PROCESS_TOKEN = secrets.token_hex(32)  # every cluster this process starts shares it (see RayCluster.token)


class RayCluster:
    """`num_nodes` Ray nodes (one head) on this machine, each with `cpus_per_node` CPUs."""

    def __init__(
        self,
        ray_executable: str | os.PathLike | None = None,
        *,
        num_nodes: int = 2,
        cpus_per_node: int = 1,
        object_store_memory: int = OBJECT_STORE_BYTES,
        timeout: float = 120.0,
        grace: float = 20.0,
        base_dir: str | os.PathLike | None = None,
        keep_dir: bool = False,
        extra_env: dict[str, str] | None = None,
    ):
        if num_nodes < 1 or num_nodes > 250:
            raise ValueError("num_nodes must be 1..250")
        self.ray_executable = None if ray_executable is None else Path(ray_executable)
        self.num_nodes, self.cpus_per_node, self.object_store_memory = num_nodes, cpus_per_node, object_store_memory
        self.timeout, self.grace, self.keep_dir = timeout, grace, keep_dir
        self._base_dir_arg = None if base_dir is None else Path(base_dir)
        self.extra_env = dict(extra_env or {})
        self.token = PROCESS_TOKEN  # one per process: Ray caches the token a driver process loaded first
        self.base_dir: Path | None = None
        self.nodes: list[_Node] = []
        self.node_info: list[dict] = []  # from ray.nodes() once up: id, ip, resources
        self.ray_version: str | None = None
        self.startup_seconds: float | None = None
        self.leftovers: list[int] = []  # pids that needed SIGKILL when stopping
        self._created_dir = False

    # -- what a driver needs -------------------------------------------------------------------------------------
    @property
    def address(self) -> str:
        """The head's GCS address, for ray.init(address=...) and `ray start --address=...`."""
        return f"{HEAD_IP}:{self.nodes[0].ports['port']}"

    @property
    def driver_env(self) -> dict[str, str]:
        """Environment variables a driver needs: the cluster's token, and RAY_ADDRESS once the cluster has started
        (so that ray.init(address="auto") finds this cluster, as it finds the one `ray start` started on a node)."""
        env = {"RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": self.token, "RAY_USAGE_STATS_ENABLED": "0"}
        if self.nodes:
            env["RAY_ADDRESS"] = self.address
        return env

    def apply_driver_env(self) -> dict[str, str | None]:
        """Put driver_env into os.environ for a driver in this process; returns the old values for restore_env.
        Ray caches what these say (see _refresh_ray_auth), so its caches are refreshed too."""
        saved = {key: os.environ.get(key) for key in self.driver_env}
        os.environ.update(self.driver_env)
        _refresh_ray_auth()
        return saved

    @staticmethod
    def restore_env(saved: dict[str, str | None]) -> None:
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value
        _refresh_ray_auth()

    @property
    def node_ips(self) -> list[str]:
        return [node.ip for node in self.nodes]

    def node_of_worker(self, pid: int) -> str | None:
        """The ip of the node that ran the Ray worker process `pid` (a task's os.getpid()), from the worker log files
        each raylet names after its workers' pids (session_*/logs/worker-<id>-<job>-<pid>.out and
        python-core-worker-<id>_<pid>.log); None when no node's logs name it."""
        for node in self.nodes:
            logs = list(node.temp_dir.glob("session_*/logs"))
            if any(
                next(folder.glob(pattern), None) is not None
                for folder in logs
                for pattern in (f"worker-*-{pid}.out", f"worker-*-{pid}.err", f"python-core-worker-*_{pid}.log")
            ):
                return node.ip
        return None

    @property
    def pids(self) -> list[int]:
        """The `ray start` processes this cluster started (each the leader of its own process group)."""
        return [node.proc.pid for node in self.nodes if node.proc is not None]

    # -- start ---------------------------------------------------------------------------------------------------
    def _resolve_ray(self) -> Path:
        if self.ray_executable is None:
            if importlib.util.find_spec("ray") is None:
                _unavailable("ray is not installed in this environment (pip install 'ray>=2.9,<3')")
            found = Path(sys.executable).with_name("ray")
            if not os.access(found, os.X_OK):
                which = shutil.which("ray")
                if which is None:
                    _unavailable("ray is importable but its `ray` command is not on PATH")
                found = Path(which)
            return found
        if not os.access(self.ray_executable, os.X_OK):
            _unavailable(f"no ray executable at {self.ray_executable}")
        return self.ray_executable

    def _env(self) -> dict[str, str]:
        env = {
            key: value for key, value in os.environ.items() if key not in ("RAY_ADDRESS", "RAY_AUTH_TOKEN_PATH")
        }  # never join some other cluster
        env.update(
            {key: value for key, value in self.driver_env.items() if key != "RAY_ADDRESS"},
            RAY_GRACEFUL_SHUTDOWN_DRAIN_TIMEOUT_S="0",
            RAY_DISABLE_DOCKER_CPU_WARNING="1",
            **self.extra_env,
        )
        return env

    @staticmethod
    def _child_setup() -> None:  # runs in the child, after start_new_session made it a session/group leader
        with contextlib.suppress(Exception):
            ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)

    def _launch(self, ray: Path, node: _Node, env: dict[str, str]) -> None:
        args = [
            str(ray),
            "start",
            "--block",
            f"--node-ip-address={node.ip}",
            f"--num-cpus={self.cpus_per_node}",
            f"--object-store-memory={self.object_store_memory}",
            f"--temp-dir={node.temp_dir}",
            "--min-worker-port=0",
            "--max-worker-port=0",
            "--disable-usage-stats",
        ]
        if node.index == 0:
            args += ["--head", "--include-dashboard=false"]
        else:
            args += [f"--address={self.address}"]
        args += [f"--{key}={value}" for key, value in node.ports.items()]
        node.temp_dir.mkdir(parents=True, exist_ok=True)
        with open(node.log, "wb") as out:
            node.proc = subprocess.Popen(
                args,
                stdin=subprocess.DEVNULL,
                stdout=out,
                stderr=subprocess.STDOUT,
                env=env,
                cwd=self.base_dir,
                start_new_session=True,
                preexec_fn=self._child_setup,
            )

    def _check_alive(self) -> None:
        for node in self.nodes:
            if node.proc is not None and node.proc.poll() is not None:
                raise ClusterError(f"`ray start` of {node.name} exited with {node.proc.returncode}\n{self.logs()}")

    def _wait_for_port(self, host: str, port: int, deadline: float) -> None:
        while time.monotonic() < deadline:
            self._check_alive()
            with contextlib.suppress(OSError), socket.create_connection((host, port), timeout=1):
                return
            time.sleep(0.2)
        raise ClusterError(f"the head's GCS never listened on {host}:{port}\n{self.logs()}")

    def start(self) -> RayCluster:
        ray = self._resolve_ray()
        if not sys.platform.startswith("linux"):
            _unavailable("a multi-node Ray cluster on one machine needs Linux (127.0.0.x on lo)")
        started = time.monotonic()
        if self._base_dir_arg is None:
            self.base_dir = Path(tempfile.mkdtemp(prefix="rpray-", dir="/tmp"))  # short: Unix socket paths
            self._created_dir = True
        else:
            self.base_dir = self._base_dir_arg
            self.base_dir.mkdir(parents=True, exist_ok=True)
        ports = _free_ports(len(_HEAD_PORTS) + len(_NODE_PORTS) * self.num_nodes)
        for i in range(self.num_nodes):
            names = (_HEAD_PORTS + _NODE_PORTS) if i == 0 else _NODE_PORTS
            mine, ports = ports[: len(names)], ports[len(names) :]
            ip = f"127.0.0.{2 + i}"
            self.nodes.append(
                _Node(
                    i,
                    ip,
                    dict(zip(names, mine)),
                    self.base_dir / f"n{i}",
                    self.base_dir / f"{'head' if i == 0 else f'node{i}'}.out",
                )
            )
        env = self._env()
        deadline = started + self.timeout
        try:
            self._launch(ray, self.nodes[0], env)
            self._wait_for_port(HEAD_IP, self.nodes[0].ports["port"], deadline)
            for node in self.nodes[1:]:
                self._launch(ray, node, env)
            self._wait_for_nodes(ray, env, deadline)
        except BaseException:
            self.stop(failed=True)
            raise
        self.startup_seconds = time.monotonic() - started
        return self

    def _wait_for_nodes(self, ray: Path, env: dict[str, str], deadline: float) -> None:
        """A driver in the Ray venv's python connects and waits until all nodes are alive."""
        left = max(deadline - time.monotonic(), 5.0)
        probe = subprocess.Popen(
            [_python_of(ray), "-c", _PROBE, self.address, str(self.num_nodes), str(left)],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=env,
            cwd=self.base_dir,
        )
        while probe.poll() is None:
            if time.monotonic() > deadline + 30:
                probe.kill()
                probe.wait()
                raise ClusterError(f"the probe driver hung for {self.timeout + 30:.0f} s\n{self.logs()}")
            try:
                self._check_alive()
            except ClusterError:
                probe.kill()
                probe.wait()
                raise
            time.sleep(0.2)
        out, err = probe.communicate()
        try:
            found = json.loads(out.strip().splitlines()[-1])
        except (ValueError, IndexError):
            raise ClusterError(
                f"the probe driver failed (exit {probe.returncode}):\n{err[-3000:]}\n{self.logs()}"
            ) from None
        self.ray_version, self.node_info = found["ray"], found["nodes"]
        if len(self.node_info) < self.num_nodes:
            raise ClusterError(
                f"{len(self.node_info)} of {self.num_nodes} nodes alive after {self.timeout:.0f} s: "
                f"{self.node_info}\n{self.logs()}"
            )

    # -- logs ----------------------------------------------------------------------------------------------------
    def logs(self, lines: int = 25) -> str:
        parts = []
        for node in self.nodes:
            parts.append(f"--- {node.name} ({node.ip}): `ray start` output {node.log}\n{_tail(node.log, lines)}")
            for name in ("gcs_server.err", "gcs_server.out", "raylet.err", "raylet.out"):
                for path in sorted(node.temp_dir.glob(f"session_*/logs/{name}")):
                    parts.append(f"--- {node.name}: {path}\n{_tail(path, lines)}")
        return "\n".join(parts)

    # -- stop ----------------------------------------------------------------------------------------------------
    def stop(self, failed: bool = False) -> None:
        started = [node for node in self.nodes if node.proc is not None]
        recorded = _descendants([node.proc.pid for node in started])  # before anything exits and is re-parented
        for node in reversed(started):  # non-head nodes first, then the head
            proc = node.proc
            if proc.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    proc.send_signal(signal.SIGTERM)
                try:
                    proc.wait(timeout=self.grace)
                except subprocess.TimeoutExpired:
                    self.leftovers.append(proc.pid)
            members = _group_members(proc.pid)  # its group: the node's daemons, workers
            if members:
                self.leftovers.extend(members)
                with contextlib.suppress(ProcessLookupError, PermissionError):
                    os.killpg(proc.pid, signal.SIGKILL)
            with contextlib.suppress(subprocess.TimeoutExpired):
                proc.wait(timeout=10)
        for pid, start in recorded.items():  # descendants that left the group (none seen with Ray 2.60)
            if _start_time(pid) == start:
                self.leftovers.append(pid)
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGKILL)
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and any(
            _start_time(p) == s and not _is_zombie(p) for p, s in recorded.items()
        ):
            time.sleep(0.1)
        self.leftovers = sorted(set(self.leftovers))
        if self._created_dir and self.base_dir is not None and not (failed or self.keep_dir):
            shutil.rmtree(self.base_dir, ignore_errors=True)

    def __enter__(self) -> RayCluster:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop(failed=exc[0] is not None)


def _is_zombie(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z"
    except OSError:
        return True


def main(argv: list[str] | None = None) -> int:
    import argparse

    parser = argparse.ArgumentParser(description="Start a local multi-node Ray cluster until Enter or a signal.")
    parser.add_argument("--ray", help="the ray executable (default: the one of this python)")
    parser.add_argument("--nodes", type=int, default=2)
    parser.add_argument("--cpus", type=int, default=1, help="CPUs per node")
    parser.add_argument("--timeout", type=float, default=120.0)
    args = parser.parse_args(argv)
    cluster = RayCluster(args.ray, num_nodes=args.nodes, cpus_per_node=args.cpus, timeout=args.timeout)

    def interrupt(*_):
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, interrupt)
    with cluster:
        print(
            json.dumps(
                {
                    "address": cluster.address,
                    "env": cluster.driver_env,
                    "ray": cluster.ray_version,
                    "startup_seconds": round(cluster.startup_seconds, 2),
                    "pids": cluster.pids,
                    "nodes": cluster.node_info,
                    "base_dir": str(cluster.base_dir),
                }
            ),
            flush=True,
        )
        with contextlib.suppress(KeyboardInterrupt):
            if sys.stdin.isatty():
                input("Enter stops the cluster\n")
            else:
                signal.pause()  # SIGTERM or SIGINT stops it
    print(json.dumps({"stopped": True, "leftovers": cluster.leftovers}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
