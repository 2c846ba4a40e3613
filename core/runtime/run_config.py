"""The run's configuration: one typed record, validated once, of everything `skinsafe run` was asked to do.

core/app/run.py builds it from the command line (argparse stays there), wires the run from it, and the record
stores it (`to_json`: the record's metadata `skinsafe`, key `run`; `from_json` reads it back, equal). A bad value
is refused with a `DesignError` naming the option and the fix. The option's link speed (`baud`) against the boards'
limit is checked where the boards are (hardware/client.py `baud_problem`, in core/app).
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields

from skinsafe.core.runtime.fault_plan import Injection
from skinsafe.core.runtime.monitor import AFTER_CONTACT, OVERRUNS
from skinsafe.core.runtime.view_stream import DEFAULT_PORT
from skinsafe.core.safety.retraction import RetractionParams
from skinsafe.core.skin.model import DesignError

ROBOTS = ("sim", "fr3")
LINK_LATENCY_FREE = 0.05  # s of --link-latency accepted without --allow-link-latency
LINK_LATENCY_MAX = 10.0
MAX_TARE_FRAMES = 10_000
TAXEL_FAULTS = ("stuck", "noisy")


@dataclass(frozen=True)
class RunConfig:
    """`skinsafe run`'s options (its --help says what each does), with the same defaults."""

    map: str
    boards: tuple[str, ...]  # ("emulate",) or every board's serial port
    command: str  # hold | trajectory:FILE.csv | teleop:[HOST:]PORT
    robot: str = "sim"
    host: str | None = None
    seconds: float | None = None
    record: str | None = None
    rate: int = 100
    link_latency: float = 0.0
    allow_link_latency: bool = False
    realtime: str = "auto"
    allow_non_realtime: bool = False
    baud: int = 1_000_000
    tare_frames: int = 100
    noise_fraction: float = 0.25
    max_excluded: float = 0.02
    command_timeout: float = 0.1
    teleop_key: str | None = None
    teleop_leader: str | None = None
    tdm: str | None = None
    alpha: float = RetractionParams.alpha
    after_contact: str = "resume"
    period: float = 0.002  # the sim's control period, s
    contact: str = "none"
    taxel_faults: tuple[tuple[int, str], ...] = ()  # (taxel, stuck | noisy) in the sim's skin
    inject: tuple[Injection, ...] = ()
    overruns: int = OVERRUNS
    feed: str | None = None
    view: bool = False
    view_port: int = 8080
    view_stream: str = f"127.0.0.1:{DEFAULT_PORT}"
    foxglove: int | None = None  # the Foxglove WebSocket server's port (0: any free one); None: none
    stats: str | None = None

    def __post_init__(self):
        problem = self._problem()
        if problem:
            raise DesignError(problem)

    def _problem(self) -> str | None:
        """The first option that cannot be run, as the line to print; None when all can."""
        if self.robot not in ROBOTS:
            return f"--robot {self.robot}: give one of {', '.join(ROBOTS)}"
        if not self.boards:
            return "--boards: give 'emulate' or the serial port of every board"
        if self.seconds is not None and not (math.isfinite(self.seconds) and self.seconds > 0):
            return f"--seconds {self.seconds}: give a positive duration"
        if not 1 <= self.rate <= 65535:
            return f"--rate {self.rate}: give frames per second per board, 1..65535"
        if not (math.isfinite(self.link_latency) and 0 <= self.link_latency <= LINK_LATENCY_MAX):
            return f"--link-latency {self.link_latency}: give 0..{LINK_LATENCY_MAX:g} s"
        if self.link_latency > LINK_LATENCY_FREE and not self.allow_link_latency:
            return (f"--link-latency {self.link_latency:g}: above {LINK_LATENCY_FREE:g} s a board may be blind that "
                    "long before it is named silent; pass --allow-link-latency to accept it (the start prints the "
                    "distance a taxel travels blind)")
        if self.overruns < 0:
            return f"--overruns {self.overruns}: give 0 (off) or the consecutive overruns that stop"
        if not 2 <= self.tare_frames <= MAX_TARE_FRAMES:
            return f"--tare-frames {self.tare_frames}: give 2..{MAX_TARE_FRAMES} (each taxel's frames are kept)"
        if self.robot == "sim":
            from skinsafe.core.sim.robot_driver import PERIOD_S

            if not (math.isfinite(self.period) and PERIOD_S[0] <= self.period <= PERIOD_S[1]):
                return f"--period {self.period}: give the sim's control period, {PERIOD_S[0]}..{PERIOD_S[1]} s"
        try:
            RetractionParams(alpha=self.alpha)
        except ValueError as e:
            return f"--alpha {self.alpha}: {e}"
        if not (0 <= self.max_excluded < 1) or not self.noise_fraction > 0:
            return "--max-excluded must be in [0, 1) and --noise-fraction positive"
        if not (math.isfinite(self.command_timeout) and self.command_timeout > 0):
            return f"--command-timeout {self.command_timeout}: give a positive time, s"
        if self.after_contact not in AFTER_CONTACT:
            return f"--after-contact {self.after_contact}: give one of {', '.join(AFTER_CONTACT)}"
        if self.foxglove is not None and not 0 <= self.foxglove <= 65535:
            return f"--foxglove {self.foxglove}: give a TCP port, 0..65535 (0: any free one), e.g. 8765"
        if self.boards != ("emulate",) and "emulate" in self.boards:
            return "--boards: give 'emulate' alone or serial ports"
        return self._robot_problem()

    def _robot_problem(self) -> str | None:
        """Options that only one robot takes, and what a hardware robot refuses."""
        if self.robot == "fr3" and self.after_contact == "always-resume" and not (self.allow_non_realtime and self.feed):
            return ("--after-contact always-resume resumes the plan after every retraction, flagged or not: refused on "
                    "a hardware robot; use resume or hold (a simulated robot, franky-sim with its world's --feed and "
                    "--allow-non-realtime, accepts it for benches)")
        if self.robot == "sim" and self.host:
            return "--host is for --robot fr3"
        if self.robot == "fr3" and self.boards == ("emulate",) and not self.feed:
            return ("--robot fr3 --boards emulate needs --feed NAME: the force feed of the robot's simulated world "
                    "(franky_world serve prints it)")
        bad = [f"{kind}:{i}" for i, kind in self.taxel_faults if kind not in TAXEL_FAULTS or i < 0]
        if bad:
            return f"--taxel-fault {bad[0]}: give stuck:TAXEL or noisy:TAXEL (a taxel index)"
        sim_only = [o for o, v in (("--contact", self.contact != "none"), ("--taxel-fault", self.taxel_faults),
                                   ("--inject sim-*", any(i.kind.startswith("sim-") for i in self.inject))) if v]
        if self.robot != "sim" and sim_only:
            return f"{', '.join(sim_only)}: for --robot sim only"
        if self.robot != "fr3" and any(i.kind.startswith("robot-") for i in self.inject):
            return "--inject robot-*: for --robot fr3 only (the sim's are sim-*)"
        return None

    def to_json(self) -> dict:
        """Its fields as JSON values (lists for tuples, each injection as {kind, at, board}), in field order."""
        doc = asdict(self)
        doc["boards"] = list(self.boards)
        doc["taxel_faults"] = [list(x) for x in self.taxel_faults]
        doc["inject"] = [asdict(i) for i in self.inject]
        return doc

    @classmethod
    def from_json(cls, doc: dict) -> RunConfig:
        """From a record's `run` (`to_json`); a key this skinsafe does not know is refused by name."""
        known = [f.name for f in fields(cls)]
        unknown = sorted(set(doc) - set(known))
        if unknown:
            raise DesignError(f"run configuration: unknown keys {unknown}; this skinsafe knows {known}")
        return cls(**{**doc, "boards": tuple(doc["boards"]),
                      "taxel_faults": tuple((int(i), str(k)) for i, k in doc.get("taxel_faults", ())),
                      "inject": tuple(Injection(**i) for i in doc.get("inject", ()))})
