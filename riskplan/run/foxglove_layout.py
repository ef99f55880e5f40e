"""`foxglove_layout.json`: a Foxglove layout for a run's `run.mcap` (import it in Foxglove: Layouts > Import).

    write_layout(run_dir, robots=3, size=(12, 12)) -> run_dir / "foxglove_layout.json"

The layout (Foxglove's layout JSON: `configById` panel configs and a `layout` tree of splits) holds

- a 3D panel in frame "grid" with `/world/map`, `/world/markers` and `/paths` (the world and the sampled paths),
- a 3D panel in frame "team" with `/team/graph` (the communication graph has a frame of its own),
- plot panels of `/metrics{robot==r}.cvar` and `/metrics{robot==r}.mean` per robot (r = -1 is a team's network
  average; at most `MAX_ROBOT_SERIES` robots are drawn one by one) and, for a team, `/consensus_error`,
- a raw message panel on `/summary`.

Every topic it names is one `riskplan.run.record` writes (`riskplan.run.log_format` names them) into every run's log (`topics(layout)` lists them).
"""

from __future__ import annotations

import json
import re
from pathlib import Path

from riskplan.run import log_format
from riskplan.run.foxglove_scene import FRAME
from riskplan.run.run_files import LAYOUT as LAYOUT_FILE
from riskplan.util.paths import write_atomic

TEAM_FRAME = "team"
MAX_ROBOT_SERIES = 8  # more lines than this make a plot unreadable: the team average stands for the rest
# Okabe-Ito (as the report): one colour per series
COLORS = ("#000000", "#0072B2", "#D55E00", "#009E73", "#CC79A7", "#56B4E9", "#E69F00", "#F0E442", "#999999")

GRID_PANEL = "3D!riskplan-grid"
TEAM_PANEL = "3D!riskplan-team"
CVAR_PANEL = "Plot!riskplan-cvar"
MEAN_PANEL = "Plot!riskplan-mean"
CONSENSUS_PANEL = "Plot!riskplan-consensus"
SUMMARY_PANEL = "RawMessages!riskplan-summary"


def series_robots(robots: int) -> list[int]:
    """The robot ids plotted: 0 for one robot; the network average -1 and the first robots for a team."""
    if robots <= 1:
        return [0]
    return [-1] + list(range(min(robots, MAX_ROBOT_SERIES)))


def _series(value: str, label: str, color: str) -> dict:
    """One line of a plot panel: a message path, drawn at each message's receive time."""
    return {"value": value, "enabled": True, "timestampMethod": "receiveTime", "label": label, "color": color}


def _plot(title: str, field: str, robots: int) -> dict:
    paths = [
        _series(
            f"{log_format.METRICS}{{robot=={r}}}.{field}",
            "team average" if r == -1 else f"robot {r}",
            COLORS[i % len(COLORS)],
        )
        for i, r in enumerate(series_robots(robots))
    ]
    return {
        "title": title,
        "paths": paths,
        "showXAxisLabels": True,
        "showYAxisLabels": True,
        "showLegend": True,
        "legendDisplay": "floating",
        "showPlotValuesInLegend": False,
        "isSynced": True,
        "xAxisVal": "timestamp",
        "sidebarDimension": 240,
    }


def _scene(title: str, frame: str, topics: dict[str, dict], target: tuple[float, float], distance: float) -> dict:
    return {
        "title": title,
        "cameraState": {
            "distance": distance,
            "perspective": False,
            "phi": 0.0,
            "thetaOffset": 0.0,
            "target": [target[0], target[1], 0.0],
            "targetOffset": [0.0, 0.0, 0.0],
            "targetOrientation": [0.0, 0.0, 0.0, 1.0],
            "fovy": 45.0,
            "near": 0.5,
            "far": 5000.0,
        },
        "followMode": "follow-pose",
        "followTf": frame,
        "scene": {"enableStats": False},
        "transforms": {},
        "topics": {topic: {"visible": True, **settings} for topic, settings in topics.items()},
        "layers": {"grid": {"visible": False, "layerId": "foxglove.Grid"}},  # the world map is the grid
        "publish": {"type": "point"},
        "imageMode": {},
    }


def _split(direction: str, panels: list, sizes: list[float] | None = None):
    """Foxglove's layout tree: nested binary splits; `sizes` are the shares of the panels (default equal)."""
    if len(panels) == 1:
        return panels[0]
    sizes = sizes or [1.0] * len(panels)
    first = sizes[0] / sum(sizes)
    return {
        "first": panels[0],
        "second": _split(direction, panels[1:], sizes[1:]),
        "direction": direction,
        "splitPercentage": round(100 * first, 2),
    }


def layout(robots: int = 1, size: tuple[int, int] = (12, 12)) -> dict:
    """The layout of a run of `robots` robots on a `size` (width, height) grid."""
    width, height = (int(size[0]), int(size[1])) if size else (12, 12)
    config = {
        GRID_PANEL: _world_scene(width, height),
        TEAM_PANEL: _scene("communication graph", TEAM_FRAME, {log_format.NETWORK_SCENE: {}}, (5.0, 5.0), 16.0),
        CVAR_PANEL: _plot("CVaR of the training batch per iteration", "cvar", robots),
        MEAN_PANEL: _plot("mean of the training batch per iteration", "mean", robots),
        SUMMARY_PANEL: {
            "title": "summary.json",
            "topicPath": log_format.SUMMARY,
            "diffEnabled": False,
            "diffMethod": "custom",
            "diffTopicPath": "",
            "showFullMessageForDiff": False,
            "expansion": "all",
        },
    }
    plots = [CVAR_PANEL, MEAN_PANEL]
    if robots > 1:
        config[CONSENSUS_PANEL] = {
            **_plot("consensus error max ||θ_i − θ_j||", "consensus_error", 1),
            "paths": [_series(f"{log_format.CONSENSUS}.consensus_error", "consensus error", COLORS[0])],
        }
        plots.append(CONSENSUS_PANEL)
    left = _split("column", [GRID_PANEL, TEAM_PANEL], [3, 1])
    right = _split("column", plots + [SUMMARY_PANEL])
    return {
        "configById": config,
        "globalVariables": {},
        "userNodes": {},
        "linkedGlobalVariables": [],
        "playbackConfig": {"speed": 1, "messageOrder": "receiveTime"},
        "layout": _split("row", [left, right], [3, 2]),
    }


def _world_scene(width: int, height: int) -> dict:
    """The 3D panel of the grid: the map coloured by cell kind, the markers and the sampled paths, all in view."""
    world_map = {
        "colorField": "cell",
        "colorMode": "colormap",
        "colorMap": "turbo",
        "minValue": 0,
        "maxValue": 2,
        "frameLocked": True,
    }
    return _scene(
        "world, sources and sampled paths",
        FRAME,
        {log_format.WORLD_MAP: world_map, log_format.WORLD_MARKERS: {}, log_format.PATHS: {}},
        (width / 2, height / 2),
        1.6 * max(width, height, 1),
    )


def layout_for(config: dict) -> dict:
    """The layout of a run with this config (a dict as in .hydra/config.yaml)."""
    team = config.get("team") if isinstance(config.get("team"), dict) else {}
    world = config.get("world") if isinstance(config.get("world"), dict) else {}
    robots = team.get("robots", 1)
    size = world.get("size", (12, 12))
    try:
        robots = int(robots)
        size = (int(size[0]), int(size[1]))
    except (TypeError, ValueError, IndexError, KeyError):
        robots, size = 1, (12, 12)
    return layout(robots, size)


def write_layout(run_dir: Path | str, robots: int = 1, size: tuple[int, int] = (12, 12), durable: bool = True) -> Path:
    """Write `foxglove_layout.json` into a run directory (atomically; synced unless not `durable`) and return its
    path."""
    path = Path(run_dir) / LAYOUT_FILE
    write_atomic(path, json.dumps(layout(robots, size), indent=2) + "\n", durable)
    return path


_TOPIC = re.compile(r"^(/[A-Za-z0-9_/]*?)(?=[.{\[]|$)")


def topics(data: dict) -> set[str]:
    """Every topic a layout's panels read (3D panel topics, plot series, raw message panels)."""
    found: set[str] = set()
    for panel in data.get("configById", {}).values():
        found.update(panel.get("topics", {}).keys())
        for path in panel.get("paths", []):
            match = _TOPIC.match(path.get("value", ""))
            if match:
                found.add(match.group(1))
        if panel.get("topicPath"):
            match = _TOPIC.match(panel["topicPath"])
            if match:
                found.add(match.group(1))
    return found


def panels(tree) -> list[str]:
    """The panel ids in a layout tree, left to right."""
    if isinstance(tree, str):
        return [tree]
    return panels(tree["first"]) + panels(tree["second"])
