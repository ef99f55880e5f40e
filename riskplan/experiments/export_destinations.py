"""Where `riskplan export` writes, checked before anything is written: the target (--to), its destination (--uri:
an MLflow store, file or database or server; a TensorBoard folder), the MLflow experiment's name, the optional
package a target needs, and MLflow's settings while it writes. Each refusal is one line (BadInput). Then, as it
writes: the folder it writes into and its writers' lock, and which failures are the destination's (they stop the
export) rather than one run's."""

from __future__ import annotations

import contextlib
import errno
import os
import re
import socket
from importlib.metadata import entry_points
from pathlib import Path
from urllib.parse import unquote, urlparse

from riskplan.util import lock
from riskplan.util.checks import require_installed
from riskplan.util.errors import BadInput, did_you_mean
from riskplan.util.paths import MARKER, check_output_dir, check_output_file

TARGETS = ("mlflow", "tensorboard", "foxglove", "ros2")
DEFAULT_URI = {"mlflow": Path("outputs") / "mlruns", "tensorboard": Path("outputs") / "tensorboard"}
EXTRA = {
    "mlflow": ("mlflow", "mlflow-skinny"),
    "tensorboard": ("tensorboard", "tensorboard"),
    "ros2": ("mcap_ros2", "mcap-ros2-support"),
}
URI_SCHEME = re.compile(r"^[A-Za-z][A-Za-z0-9+.-]*:")  # file:, sqlite:, http:, databricks: (not C:\...)


def check_target(to: str | None) -> str:
    """--to: one of TARGETS."""
    if to is None or not str(to).strip():
        raise BadInput("--to", f"missing; expected one of {', '.join(TARGETS)}, e.g. --to mlflow")
    name = str(to).strip().lower()
    if name not in TARGETS:
        raise BadInput("--to", f"got '{to}'; expected one of {', '.join(TARGETS)}{did_you_mean(to, TARGETS)}")
    return name


def check_uri(to: str, uri: str | None) -> str:
    """--uri for a target: an MLflow tracking URI or store directory, a TensorBoard log directory, nothing for
    foxglove, the bags' folder for ros2 (the command's --out). Returns the destination: a tracking URI (mlflow) or a
    directory (tensorboard, ros2), '' for foxglove and for ros2 into each run directory."""
    if to == "ros2":
        return "" if uri is None else str(check_output_dir(uri, "--out").expanduser().absolute())
    if to == "foxglove":
        if uri is not None:
            raise BadInput(
                "--uri", "--to foxglove writes foxglove_layout.json into each run directory and takes no --uri"
            )
        return ""
    if uri is None:
        uri = str(DEFAULT_URI[to])
    text = str(uri)
    if URI_SCHEME.match(text) and not text.startswith("file:"):
        if to == "tensorboard":  # its writer takes any text for a folder: http://x/tb became ./http:/x/tb
            raise BadInput(
                "--uri", f"{text}: TensorBoard writes a local folder, not a URI: give its path, e.g. /data/tb"
            )
        return check_tracking_uri(text)
    if text.startswith("file:"):  # a file URI names a directory, for TensorBoard as for MLflow
        text = _file_uri_path(text)
    check_output_dir(text, "--uri")
    directory = Path(os.path.abspath(os.path.expanduser(text)))
    ours, what, example = {
        "mlflow": (_is_mlflow_store, "an MLflow file store", "an MLflow store (e.g. outputs/mlruns)"),
        "tensorboard": (
            _is_tensorboard_export,
            "a TensorBoard export",
            "one riskplan export wrote (e.g. outputs/tensorboard)",
        ),
    }[to]
    if directory.is_dir() and any(p.name != lock.LOCK for p in directory.iterdir()) and not ours(directory):
        raise BadInput("--uri", f"{uri} holds files that are not {what}; give a new or empty directory, or {example}")
    return str(directory) if to == "tensorboard" else directory.as_uri()


def _parsed(uri: str):
    """urlparse of --uri, and its port read: BadInput for what it refuses (an unclosed '[', a port past 65535)."""
    try:
        parts = urlparse(uri)
        parts.port  # noqa: B018 - read to check it
    except ValueError as err:
        raise BadInput(
            "--uri", f"{uri} is not a valid URI ({err}); e.g. http://localhost:5000 or file:///data/mlruns"
        ) from None
    return parts


def _file_uri_path(uri: str) -> str:
    """The local path of a file: URI; BadInput for one naming another host, whose path would be written here."""
    parts = _parsed(uri)
    if not uri.startswith("file://"):
        return uri[len("file:") :]
    if parts.netloc not in ("", "localhost"):
        raise BadInput(
            "--uri", f"{uri} names the host {parts.netloc}; give a local path, e.g. file:///data/mlruns (three slashes)"
        )
    return unquote(parts.path)


# MLflow's own tracking URI schemes (its tracking store registry); a database's may add a driver: mysql+pymysql
DATABASES = ("sqlite", "postgresql", "mysql", "mssql")
TRACKING_SCHEMES = ("http", "https", "databricks", "databricks-uc", "uc", *DATABASES)
CONNECT_TIMEOUT = 5.0  # s: a server that does not accept a connection in this long is taken for absent


def check_tracking_uri(uri: str) -> str:
    """An MLflow tracking URI other than a file store, checked before MLflow gets it (which would retry for minutes,
    or take any text): a scheme MLflow or a plugin knows, a server that accepts a connection, a SQLite database file
    that can be written."""
    parts = _parsed(uri)
    scheme = parts.scheme.lower()
    schemes = {*TRACKING_SCHEMES, *(e.name for e in entry_points(group="mlflow.tracking_store"))}
    if scheme not in schemes and scheme.split("+")[0] not in DATABASES:
        raise BadInput(
            "--uri",
            f"{uri}: MLflow knows no scheme '{scheme}'; give a folder, http://host:5000 or sqlite:///mlflow.db"
            f"{did_you_mean(scheme, schemes)}",
        )
    if scheme in ("http", "https"):
        _check_reachable(uri, parts)
    elif scheme.split("+")[0] == "sqlite":
        database = parts.path[1:]  # SQLAlchemy's sqlite:///relative.db, sqlite:////absolute.db
        if database in ("", ":memory:"):
            raise BadInput(
                "--uri", f"{uri} is a database in memory, gone when the export ends; give a file: sqlite:///mlflow.db"
            )
        check_output_file(database, "--uri", "in .db")
    return uri


def _check_reachable(uri: str, parts) -> None:
    """BadInput unless the server of an http(s) URI accepts a TCP connection within CONNECT_TIMEOUT."""
    if not parts.hostname:
        raise BadInput("--uri", f"{uri} names no server; e.g. http://localhost:5000")
    port = parts.port or (443 if parts.scheme.lower() == "https" else 80)
    try:
        socket.create_connection((parts.hostname, port), timeout=CONNECT_TIMEOUT).close()
    except OSError as err:
        raise BadInput(
            "--uri",
            f"{uri}: no server answers at {parts.hostname}:{port} ({err.strerror or err}); start the MLflow server "
            f"(mlflow server --port {port}) or give another --uri",
        ) from None


def check_experiment(name: str) -> None:
    """--experiment: a name MLflow takes (at most its MAX_EXPERIMENT_NAME_LENGTH printable characters), checked
    before the store is opened: MLflow would refuse it after making the store's folder."""
    from mlflow.utils.validation import MAX_EXPERIMENT_NAME_LENGTH  # optional: the mlflow extra

    if len(name) > MAX_EXPERIMENT_NAME_LENGTH:
        raise BadInput(
            "--experiment",
            f"is {len(name)} characters long; MLflow takes a name of at most {MAX_EXPERIMENT_NAME_LENGTH}",
        )
    if not name.isprintable():
        raise BadInput("--experiment", f"got {name!r}; give a name of printable characters, e.g. riskplan")


def _is_mlflow_store(directory: Path) -> bool:
    """An MLflow file store: experiment folders with a meta.yaml, or its .trash."""
    return (directory / ".trash").is_dir() or any(p.is_file() for p in directory.glob("*/meta.yaml"))


def _is_tensorboard_export(directory: Path) -> bool:
    """A TensorBoard log directory: riskplan's run folders (with their marker), or another writer's event files."""
    return any(
        p.is_file()
        for pattern in (f"*/{MARKER}", "events.out.tfevents.*", "*/events.out.tfevents.*")
        for p in directory.glob(pattern)
    )


def check_installed(to: str) -> None:
    """The optional package a target needs; MissingExtra (bad input) naming the pip install when it is missing."""
    if to in EXTRA:
        module, package = EXTRA[to]
        require_installed(module, f"--to {to}", f"the {package} package", to)


def _mlflow_settings(uri: str) -> dict[str, str]:
    """MLflow's settings for an export to `uri`: its file store allowed (MLflow >= 3.7 refuses it otherwise), and a
    server that stops answering given up on in about a minute (MLflow's defaults retry for minutes, silently)."""
    if uri.startswith("file:"):
        return {"MLFLOW_ALLOW_FILE_STORE": "true"}
    if uri.startswith(("http:", "https:")):
        return {"MLFLOW_HTTP_REQUEST_MAX_RETRIES": "1", "MLFLOW_HTTP_REQUEST_TIMEOUT": "30"}
    return {}


@contextlib.contextmanager
def mlflow_settings(uri: str):
    """_mlflow_settings in the environment while an export writes, each where the user set none."""
    added = {k: v for k, v in _mlflow_settings(uri).items() if k not in os.environ}
    os.environ.update(added)
    try:
        yield
    finally:
        for key in added:
            os.environ.pop(key, None)


def file_store(uri: str) -> Path | None:
    """The folder of an MLflow file store (file:///data/mlruns), None for a server's or database's store."""
    parts = urlparse(uri)
    return Path(unquote(parts.path)) if parts.scheme == "file" else None


def written_path(target: str, destination: str) -> Path | None:
    """The local folder (or SQLite file) an export writes into; None for each run directory or a server."""
    if target in ("tensorboard", "ros2"):
        return Path(destination) if destination else None
    parts = urlparse(destination)
    return file_store(destination) or (Path(parts.path[1:]) if parts.scheme.split("+")[0] == "sqlite" else None)


def one_writer(target: str, destination: str) -> contextlib.AbstractContextManager:
    """The destination directory's writers' lock, held while the runs are exported (a TensorBoard log directory, the
    bags' folder, an MLflow file store): two exports at once made two experiments of one name in a store, or failed
    on each other's temp folders. A server or database store locks itself; each run directory has its own lock."""
    directory = written_path(target, destination)
    if directory is None or (target == "mlflow" and file_store(destination) is None):
        return contextlib.nullcontext()
    return lock.hold_lock(directory, f"{target} export destination", make=True)


def store_errors(target: str) -> tuple[type[BaseException], ...]:
    """What a failure of the whole destination raises: a full or read-only disk, and MLflow's own exception (a
    server, a damaged store)."""
    if target == "mlflow":
        from mlflow.exceptions import MlflowException  # optional: the mlflow extra

        return OSError, MlflowException, ImportError  # ImportError: a store that needs the full mlflow
    return (OSError,)


# a disk that cannot take any more: every other run would fail the same way, so the export stops
WHOLE_DISK = (errno.ENOSPC, errno.EDQUOT, errno.EROFS)


def stops_export(err: Exception, target: str) -> bool:
    """Whether a failure to export one run is the destination's, which stops the export; any other (a folder in
    the way, a table not written by riskplan) is that run's own, which is skipped."""
    if isinstance(err, OSError):
        return err.errno in WHOLE_DISK
    return isinstance(err, store_errors(target))
