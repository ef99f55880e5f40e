"""One sweep job inside a launcher's worker (riskplan.experiments.sweep_worker): the config fingerprint that
recognises a finished job, job and trial folder names that stay plain and never collide, and strict status files."""

from __future__ import annotations

import json
import os

from riskplan.experiments import sweep_worker
from riskplan.experiments.sweep_worker import NAME_MAX, config_sha, folder_name, trial_folder, write_status


def test_config_fingerprint_ignores_order_and_the_hydra_node():
    assert config_sha({"a": 1, "b": {"c": 2}}) == config_sha({"b": {"c": 2}, "a": 1, "hydra": {"x": 1}})
    assert config_sha({"a": 1}) != config_sha({"a": 2})


def test_folder_names_are_plain_for_plain_values_and_never_collide():
    assert folder_name("risk.beta=0.1,seed=0") == "risk.beta=0.1,seed=0"
    assert folder_name("train.step_size.initial=1e+308") == "train.step_size.initial=1e+308"
    tricky = [
        "a/b",
        "a%2Fb",
        "a%252Fb",
        "..",
        ".",
        "",
        "a\x00b",
        "a b",
        "é",
        "%h" + "0" * 16,
        "x" * 300,
        "x" * 299 + "y",
        "x" * 253,
        "x" * 254 + "%",
        "%empty",
        ".hidden",
        "%2Ehidden",
        "a\\b",
        "a:b",
    ]
    names = [folder_name(t) for t in tricky]
    assert len(set(names)) == len(tricky)
    for name in names:
        assert "/" not in name and "\x00" not in name and name not in ("", ".", "..") and not name.startswith(".")
        assert len(name.encode()) <= NAME_MAX
        assert set(name) <= set("ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789._=,+-%")


def test_trial_folders_are_numbered_and_safe():
    assert trial_folder(7, "risk.beta=0.31") == "trial_007,risk.beta=0.31"
    assert trial_folder(12, "") == "trial_012"
    assert "/" not in trial_folder(0, "world.sources.0.name=../x")


def test_status_json_is_strict_json_and_leaves_no_temp_file(tmp_path):
    write_status(
        tmp_path,
        {
            "status": "done",
            "cvar": float("nan"),
            "figures": [1.0, float("inf"), -float("inf")],
            "nested": {"x": float("nan")},
        },
    )

    def refuse(name):
        raise AssertionError(f"non-standard JSON constant {name}")

    record = json.loads((tmp_path / "status.json").read_text(), parse_constant=refuse)
    assert record == {"status": "done", "cvar": None, "figures": [1.0, None, None], "nested": {"x": None}}
    assert [p.name for p in tmp_path.iterdir()] == ["status.json"]


def test_a_job_stopped_in_its_set_up_is_marked_interrupted_only_where_this_process_began_it(tmp_path):
    """Ctrl-C in a job's set-up (driver_watch.working raises KeyboardInterrupt there; the worker's signal handling
    is tested in sweeping/test_signal_at_spawn.py): its status.json then says interrupted, and a status another
    process wrote is left alone."""
    mine, theirs = tmp_path / "mine", tmp_path / "theirs"
    for folder, pid in ((mine, os.getpid()), (theirs, os.getpid() + 1)):
        folder.mkdir()
        write_status(folder, {"status": "running", "config_sha": "a", "pid": pid})
        sweep_worker._mark_interrupted(folder)
    assert json.loads((mine / "status.json").read_text())["status"] == "interrupted"
    assert json.loads((theirs / "status.json").read_text())["status"] == "running"
