"""The run's configuration: one frozen RunConfig built from `skinsafe run`'s command line, validated once (a bad
option refused by name), and read back equal from what the record stores (`to_json`)."""
import dataclasses
import json

import pytest

from skinsafe.core.app import run as run_cmd
from skinsafe.core.app.cli import module_args
from skinsafe.core.runtime.fault_plan import Injection
from skinsafe.core.runtime.run_config import RunConfig
from skinsafe.core.skin.model import DesignError


def config(*argv) -> RunConfig:
    return run_cmd.config(module_args(run_cmd, "skinsafe run", "", ["skin.json", "--boards", "emulate", "--command",
                                                                     "hold", *map(str, argv)], "run"))


def test_the_command_line_becomes_one_typed_config_that_the_record_gives_back_equal():
    cfg = config("--inject", "board-unplug@0.5:1", "--inject", "stack-nan@1", "--taxel-fault", "stuck:7",
                 "--contact", "poke:at=0.4", "--seconds", 2, "--after-contact", "hold", "--overruns", 0)
    assert cfg.inject == (Injection("board-unplug", 0.5, 1), Injection("stack-nan", 1.0))
    assert cfg.taxel_faults == ((7, "stuck"),) and cfg.boards == ("emulate",) and cfg.seconds == 2.0
    assert cfg.after_contact == "hold" and cfg.overruns == 0 and cfg.rate == 100  # the default, from RunConfig
    doc = json.loads(json.dumps(cfg.to_json()))  # as the record's metadata holds it
    assert doc["inject"][0] == {"kind": "board-unplug", "at": 0.5, "board": 1}
    assert RunConfig.from_json(doc) == cfg
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.seconds = 9.0
    with pytest.raises(DesignError, match="unknown keys.*'speed'"):
        RunConfig.from_json(doc | {"speed": 1.0})


@pytest.mark.parametrize("argv, named", [
    (("--seconds", 0), "--seconds 0.0: give a positive duration"),
    (("--rate", 0), "--rate 0"),
    (("--link-latency", 0.2), "pass --allow-link-latency"),
    (("--tare-frames", 1), "--tare-frames 1"),
    (("--period", 1.0), "--period 1.0"),
    (("--alpha", -1), "--alpha -1.0"),
    (("--max-excluded", 1), "--max-excluded"),
    (("--command-timeout", 0), "--command-timeout 0.0"),
    (("--overruns", -1), "--overruns -1"),
    (("--baud", 0), "--baud 0"),
    (("--host", "10.0.0.2"), "--host is for --robot fr3"),
    (("--taxel-fault", "hot:3"), "--taxel-fault hot:3"),
    (("--inject", "robot-die@1"), "--inject robot-\\*: for --robot fr3 only"),
    (("--inject", "melt@1"), "--inject 'melt@1': faults are"),
    (("--robot", "fr3", "--feed", "f", "--inject", "sim-nan@1"), "--inject sim-\\*: for --robot sim only"),
    (("--robot", "fr3", "--feed", "f", "--after-contact", "always-resume"), "refused on a hardware robot"),
    (("--robot", "fr3", "--host", "h", "--boards", "/dev/ttyACM0", "--allow-non-realtime", "--after-contact",
      "always-resume"), "refused on a hardware robot"),  # a real FR3 on a host without real-time: still refused
    (("--robot", "fr3"), "needs --feed NAME"),
])
def test_a_bad_option_is_refused_naming_it_and_the_fix(argv, named):
    with pytest.raises(DesignError, match=named):
        config(*argv)


def test_a_bad_option_is_one_line_and_exit_2(capsys):
    args = module_args(run_cmd, "skinsafe run", "", ["skin.json", "--boards", "emulate", "--command", "hold",
                                                     "--rate", "0"], "run")
    assert run_cmd.run(args) == 2
    assert capsys.readouterr().err == "skinsafe run: --rate 0: give frames per second per board, 1..65535\n"
