"""The format of `run.mcap` (riskplan.run.record writes it, riskplan.run.log_reader reads it): its channels, the
columns of the tables it holds and their dtypes, and riskplan's own JSON schemas of its messages (Foxglove's are
riskplan.run.foxglove_scene's).
"""

from __future__ import annotations

import json

from riskplan.run import foxglove_scene as fx

METRICS = "/metrics"
THETA = "/theta"
CONSENSUS = "/consensus_error"
TRAJECTORIES = "/trajectories"
EVAL = "/eval"
SUMMARY = "/summary"
WORLD_MAP = "/world/map"
WORLD_MARKERS = "/world/markers"
PATHS = "/paths"
NETWORK = "/team/network"
NETWORK_SCENE = "/team/graph"

ITERATION_TOPICS = (METRICS, THETA, CONSENSUS)
WORLD_TOPICS = (WORLD_MAP, WORLD_MARKERS, NETWORK, NETWORK_SCENE)  # written once, copied on resume

METRICS_BASE = {
    "iteration": "int64",
    "robot": "int64",
    "mean": "float64",
    "cvar": "float64",
    "value_at_risk": "float64",
    "std": "float64",
    "grad_norm": "float64",
    "step_size": "float64",
    "beta_l": "float64",
    "consensus_error": "float64",
    "samples": "int64",
    "seconds": "float64",
}
EVAL_COLUMNS = {
    "episode": "int64",
    "robot": "int64",
    "healthy": "bool",
    "total_reward": "float64",
    "risky_steps": "int64",
    "source_reached": "int64",
    "steps": "int64",
}
TRAJECTORY_COLUMNS = {
    "policy": "str",
    "episode": "int64",
    "robot": "int64",
    "step": "int64",
    "x": "int64",
    "y": "int64",
    "reward": "float64",
}

# --------------------------------------------------------------------------------------- riskplan's schemas
_FLOAT = {
    "description": "a float; NaN is null, infinities are the strings Infinity / -Infinity",
    "oneOf": [{"type": "number"}, {"type": "null"}, {"enum": ["Infinity", "-Infinity"]}],
}
_INT = {"type": "integer"}

OWN_SCHEMAS: dict[str, dict] = {
    "riskplan.Metrics": {
        "title": "riskplan.Metrics",
        "description": "One metrics.parquet row: one (iteration, robot); robot -1 is the network average.",
        "type": "object",
        "properties": {
            "iteration": _INT,
            "robot": _INT,
            "healthy": {"type": "boolean", "description": "false once the robot's fault (team.faults) started"},
            "mean": _FLOAT,
            "cvar": _FLOAT,
            "value_at_risk": _FLOAT,
            "std": _FLOAT,
            "objective": {
                **_FLOAT,
                "description": "the robot's own risk measure (risk, or team.risk.<robot>) on its samples; on the "
                "robot -1 row, the team objective: the sum over the robots",
            },
            "grad_norm": _FLOAT,
            "step_size": _FLOAT,
            "beta_l": {
                **_FLOAT,
                "description": "beta_l, the CVaR level of the iteration's gradient (risk.schedule; "
                "1 for the mean gradient); cvar and value_at_risk are at risk.beta",
            },
            "consensus_error": _FLOAT,
            "samples": _INT,
            "seconds": _FLOAT,
        },
        "patternProperties": {"^theta_[0-9]+$": _FLOAT},
        "required": ["iteration", "robot"],
    },
    "riskplan.Theta": {
        "title": "riskplan.Theta",
        "description": "Policy parameters of one robot after an iteration (robot -1: network average).",
        "type": "object",
        "properties": {"iteration": _INT, "robot": _INT, "theta": {"type": "array", "items": _FLOAT}},
        "required": ["iteration", "robot", "theta"],
    },
    "riskplan.ConsensusError": {
        "title": "riskplan.ConsensusError",
        "description": "max ||theta_i - theta_j|| of an iteration (null when there is one robot); marks it complete.",
        "type": "object",
        "properties": {"iteration": _INT, "consensus_error": _FLOAT},
        "required": ["iteration", "consensus_error"],
    },
    "riskplan.TableBatch": {
        "title": "riskplan.TableBatch",
        "description": "Rows offset..offset+rows-1 of a table, column by column, with the pandas dtype of each.",
        "type": "object",
        "properties": {
            "table": {"type": "string"},
            "offset": {"type": "integer", "minimum": 0},
            "rows": {"type": "integer", "minimum": 0},
            "dtypes": {"type": "object", "additionalProperties": {"type": "string"}},
            "columns": {
                "type": "object",
                "additionalProperties": {
                    "type": "array",
                    "items": {"type": ["number", "string", "boolean", "null"]},
                },
            },
        },
        "required": ["table", "offset", "rows", "dtypes", "columns"],
    },
    "riskplan.Network": {
        "title": "riskplan.Network",
        "description": "The team's communication graph and mixing weights (weights[i][j][m] = a^{ij}_m of eq. 14).",
        "type": "object",
        "properties": {
            "robots": _INT,
            "graph": {"type": "string"},
            "edges": {"type": "array"},
            "weights": {"type": "array"},
            "gamma": _FLOAT,
            "slem": _FLOAT,
        },
        "required": ["robots", "graph", "edges", "weights"],
    },
    "riskplan.Summary": {
        "title": "riskplan.Summary",
        "description": "summary.json of the run (free-form object).",
        "type": "object",
    },
}

TOPIC_SCHEMA = {
    METRICS: "riskplan.Metrics",
    THETA: "riskplan.Theta",
    CONSENSUS: "riskplan.ConsensusError",
    TRAJECTORIES: "riskplan.TableBatch",
    EVAL: "riskplan.TableBatch",
    SUMMARY: "riskplan.Summary",
    NETWORK: "riskplan.Network",
    NETWORK_SCENE: fx.SCENE_UPDATE,
    WORLD_MAP: fx.GRID,
    WORLD_MARKERS: fx.SCENE_UPDATE,
    PATHS: fx.SCENE_UPDATE,
}


def schema_bytes(name: str) -> bytes:
    if name in OWN_SCHEMAS:
        return json.dumps(OWN_SCHEMAS[name], separators=(",", ":")).encode()
    return fx.schema_bytes(name)
