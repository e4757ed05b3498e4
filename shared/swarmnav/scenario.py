"""The scenario schema: pydantic models for everything a scenario holds (``Scenario`` and its
tables), validated field by field; :mod:`swarmnav.config` loads TOML files into it.

One place for every number of a scenario (the paper's §3.1 set-up: configs/paper.toml). Units are SI unless the field name says
otherwise (``_deg``, ``_dph`` = deg/h, ``_ug`` = micro-g, ``_dpsh`` = deg/sqrt(h),
``_ugpshz`` = micro-g/sqrt(Hz), the PSINS ``imuerrset`` convention). Frames: ENU about the
geodetic origin, body FLU. Seed lists (``[evaluation]``, ``--seeds``) are parsed by
:func:`parse_seed_spec`.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping
from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

PositiveFloat = Annotated[float, Field(gt=0)]
NonNegFloat = Annotated[float, Field(ge=0)]
Range2 = tuple[float, float]


class _Model(BaseModel):
    # allow_inf_nan=False: an inf or nan anywhere in a scenario (e.g. duration_s = inf) is refused
    # naming its field, instead of failing deep inside the simulator
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class ScenarioMeta(_Model):
    name: str
    description: str = ""
    seed: int = Field(1, ge=0, description="run seed: drives every random draw except UAV 1's start")
    duration_s: PositiveFloat
    epoch_dt_s: PositiveFloat = 1.0
    imu_rate_hz: PositiveFloat = 100.0


def _check_range(name: str, r: Range2) -> None:
    """A [lo, hi] draw range (uniform): lo <= hi, else the simulator's draw fails."""
    if r[0] > r[1]:
        raise ValueError(f"{name}: lower bound {r[0]} must not exceed upper bound {r[1]} (a [lo, hi] range)")


class Origin(_Model):
    lat_deg: float = Field(ge=-90, le=90)
    lon_deg: float = Field(ge=-180, le=180)
    alt_m: float = 0.0


MAX_UAVS = 2000  # schema cap on swarm.n_uavs (the scale family, configs/scale.toml, goes to 1,000)


class Swarm(_Model):
    n_uavs: int = Field(ge=2, le=MAX_UAVS)
    masters: list[int] = Field(description="UAV ids (1-based) with the high-grade sensor set")
    uav1_start_enu_m: tuple[float, float, float]
    box_e_m: Range2
    box_n_m: Range2
    box_u_m: Range2
    min_separation_m: PositiveFloat = 30.0
    # scale family (configs/scale.toml); both None = the fixed box and the explicit masters list, and
    # then absent from to_dict(), so the configs written before these existed hash exactly as before
    masters_every: int | None = Field(
        None, ge=1, description="every k-th UAV is a master too: ids 1, 1+k, 1+2k, ... (valid for any n_uavs); "
                                "merged into 'masters' on validation")
    density_per_km3: PositiveFloat | None = Field(
        None, description="formation density, UAVs per km^3: the start box keeps box_u_m and the centre and "
                          "aspect of box_e_m x box_n_m, its horizontal extent scaled so that its volume is "
                          "n_uavs / density (the box grows with n_uavs); None = the box as given")

    @model_validator(mode="before")
    @classmethod
    def _every(cls, data):
        if isinstance(data, dict) and data.get("masters_every") is not None:
            try:
                k, n = int(data["masters_every"]), int(data["n_uavs"])
                listed = [int(m) for m in data.get("masters") or []]
            except (KeyError, TypeError, ValueError):
                return data  # the field validators name the problem
            if k >= 1:
                data = {**data, "masters": sorted(set(listed) | set(range(1, n + 1, k)))}
        return data

    @model_validator(mode="after")
    def _check(self) -> "Swarm":
        bad = [m for m in self.masters if not 1 <= m <= self.n_uavs]
        if bad:
            raise ValueError(f"masters {bad} are not UAV ids in 1..{self.n_uavs}")
        for name in ("box_e_m", "box_n_m", "box_u_m"):
            lo, hi = getattr(self, name)
            if lo >= hi:
                raise ValueError(f"{name}: lower bound {lo} must be below upper bound {hi}")
        if self.density_per_km3 is not None:
            # random sequential placement jams near a 38 % volume fraction of the min-separation
            # spheres; refuse above 25 % (it would spin through 20,000 draws per UAV and fail)
            lo, hi = self.formation_box()
            frac = self.n_uavs * (np.pi / 6.0) * self.min_separation_m**3 / float(np.prod(hi - lo))
            if frac > 0.25:
                raise ValueError(f"density_per_km3 {self.density_per_km3:g} is too dense for min_separation_m "
                                 f"{self.min_separation_m:g} (spheres fill {frac:.0%} of the box; at most 25 %)")
        return self

    def formation_box(self) -> tuple["np.ndarray", "np.ndarray"]:
        """(lo, hi) ENU corners of the box the formation is drawn in (see ``density_per_km3``)."""
        lo = np.array([self.box_e_m[0], self.box_n_m[0], self.box_u_m[0]], float)
        hi = np.array([self.box_e_m[1], self.box_n_m[1], self.box_u_m[1]], float)
        if self.density_per_km3 is None:
            return lo, hi
        vol = self.n_uavs / self.density_per_km3 * 1e9  # m^3
        f = np.sqrt(vol / float(np.prod(hi - lo)))
        mid, half = (lo + hi) / 2.0, (hi - lo) / 2.0
        half[:2] *= f
        return mid - half, mid + half

    def role(self, uav: int) -> Literal["master", "slave"]:
        return "master" if uav in self.masters else "slave"


class Manoeuvre(_Model):
    """One leg of the formation-centre flight plan, flown after the initial acceleration."""

    kind: Literal["straight", "turn", "climb", "s_turn"]
    duration_s: PositiveFloat
    turn_deg: float = 0.0  # turn: heading change (positive = right/clockwise seen from above)
    climb_rate_mps: float = 0.0  # climb: vertical speed (negative = descent)
    s_amplitude_deg: float = 0.0  # s_turn: peak heading deviation
    s_period_s: float = 60.0  # s_turn: period of the heading oscillation


class Trajectory(_Model):
    initial_heading_deg: float = 90.0  # 0 = north, 90 = east
    cruise_speed_mps: PositiveFloat = 15.0
    accel_time_s: PositiveFloat = 20.0
    wander_amplitude_m: NonNegFloat = 10.0
    wander_period_s: tuple[float, float] = (60.0, 240.0)  # range the per-UAV wander periods are drawn from
    manoeuvres: list[Manoeuvre] = Field(default_factory=list)


class ImuSpec(_Model):
    """PSINS imuerrset(eb, db, web, wdb) plus bias random walk."""

    gyro_bias_dph: NonNegFloat
    accel_bias_ug: NonNegFloat
    arw_dpsh: NonNegFloat
    vrw_ugpshz: NonNegFloat
    gyro_bias_rw_dphpsh: NonNegFloat = 0.0  # bias random walk, deg/h per sqrt(h)
    accel_bias_rw_ugpssh: NonNegFloat = 0.0  # bias random walk, micro-g per sqrt(s)


class GnssSpec(_Model):
    rate_hz: PositiveFloat = 1.0
    pos_sigma_m: tuple[NonNegFloat, NonNegFloat, NonNegFloat]  # white, E N U
    gm_sigma_m: NonNegFloat = 0.0  # first-order Gauss-Markov bias, per axis
    gm_tau_s: PositiveFloat = 120.0
    vel_sigma_mps: NonNegFloat


class UwbSpec(_Model):
    sigma_m: PositiveFloat = 0.10
    link_bias_sigma_m: NonNegFloat = 0.05
    max_range_m: PositiveFloat = 400.0
    packet_loss: float = Field(0.02, ge=0, lt=1)


class RelSpec(_Model):
    sigma_deg: PositiveFloat = 1.0
    max_range_m: PositiveFloat = 300.0


class Sensors(_Model):
    imu: dict[Literal["master", "slave"], ImuSpec]
    gnss: dict[Literal["master", "slave"], GnssSpec]
    uwb: UwbSpec = UwbSpec()
    rel: RelSpec = RelSpec()

    @model_validator(mode="after")
    def _roles(self) -> "Sensors":
        for name in ("imu", "gnss"):
            missing = {"master", "slave"} - set(getattr(self, name))
            if missing:
                raise ValueError(f"{name}: no spec for role(s) {sorted(missing)}")
        return self


class Interference(_Model):
    """Fault 1: every link switches in/out of an interfered (NLOS) state, two-state Markov."""

    enabled: bool = True
    mean_dwell_s: PositiveFloat = 20.0
    time_fraction: float = Field(0.10, ge=0, lt=1)
    bias_m: Range2 = (1.0, 8.0)
    noise_scale: PositiveFloat = 5.0

    @model_validator(mode="after")
    def _check(self) -> "Interference":
        _check_range("bias_m", self.bias_m)
        return self


class ModuleFailure(_Model):
    """Fault 2: every range UAV `uav` takes part in is truth + U(error_m) (new draw each time)."""

    uav: int = Field(ge=1)
    start_s: NonNegFloat
    end_s: NonNegFloat
    error_m: Range2 = (20.0, 150.0)

    @model_validator(mode="after")
    def _check(self) -> "ModuleFailure":
        _check_range("error_m", self.error_m)
        return self


class StuckModule(_Model):
    """Fault 3: UAV `uav`'s module repeats the range it measured at `start_s`."""

    uav: int = Field(ge=1)
    start_s: NonNegFloat
    end_s: NonNegFloat


class Drift(_Model):
    """Fault 4: link `link` gains a bias growing `rate_mps` over [start_s, end_s], then clears."""

    link: tuple[int, int]
    start_s: NonNegFloat
    end_s: NonNegFloat
    rate_mps: float = 0.05


class GnssOutage(_Model):
    uavs: Literal["slaves", "masters", "all"] | list[int] = "slaves"
    start_s: NonNegFloat
    end_s: NonNegFloat


class ProcessKill(_Model):
    """Distributed runs only: SIGKILL the UAV's process at `at_s`; restart at `restart_s` if given."""

    uav: int = Field(ge=1)
    at_s: NonNegFloat
    restart_s: float | None = None


class UwbErrorModel(_Model):
    """Which UWB ranging error model the simulator draws from (``[faults.uwb]``; docs/uwb-errors.md).

    ``gaussian`` (what a config without this table gets): core N(0, sensors.uwb.sigma_m), faults as
    configured (``faults.interference`` is the paper's long, large interference). ``realistic``: the
    statistics of public two-way-ranging recordings (MILUV, MURP, UTIL): a heavy-tailed zero-mean core
    (Student-t, labelled clean) plus short NLOS episodes with a positive bias (labelled faulty,
    FaultKind.INTERFERENCE); it replaces ``faults.interference``, which must then be disabled.
    """

    model: Literal["gaussian", "realistic"] = Field(
        "gaussian", description="UWB ranging error model: 'gaussian' (legacy) or 'realistic'")
    core_dof: float = Field(
        3.0, gt=2.0, le=1000.0,
        description="realistic: degrees of freedom ν of the Student-t core (dimensionless); the core is scaled "
                    "so its robust spread (1.4826·MAD) equals sensors.uwb.sigma_m; std/spread = 1.53 at ν = 3")
    nlos_fraction: float = Field(
        0.03, ge=0.0, lt=1.0,
        description="realistic: share of link time inside an NLOS episode (= expected share of ranges, dimensionless)")
    nlos_mean_duration_s: PositiveFloat = Field(
        0.5, description="realistic: mean length of an NLOS episode, s (exponential; continuous time, "
                         "independent of the epoch length)")
    nlos_bias_m: Range2 = Field(
        (0.5, 1.9), description="realistic: support [lo, hi] of the per-episode NLOS bias, m (positive: NLOS "
                                "lengthens the path)")
    nlos_bias_median_m: PositiveFloat = Field(
        0.75, description="realistic: median of the per-episode NLOS bias, m (a truncated exponential on "
                          "nlos_bias_m with this median)")

    @model_validator(mode="after")
    def _check(self) -> "UwbErrorModel":
        lo, hi = self.nlos_bias_m
        if not 0.0 <= lo < hi:
            raise ValueError(f"nlos_bias_m: need 0 <= lo < hi, got {self.nlos_bias_m}")
        if not lo < self.nlos_bias_median_m < hi:
            raise ValueError(f"nlos_bias_median_m {self.nlos_bias_median_m} must lie inside nlos_bias_m {self.nlos_bias_m}")
        if self.nlos_bias_median_m >= (lo + hi) / 2:
            raise ValueError("nlos_bias_median_m must be below the middle of nlos_bias_m (a right-skewed bias: "
                             "a truncated exponential cannot have a larger median)")
        return self


class Faults(_Model):
    interference: Interference = Interference(enabled=False)
    module_failure: list[ModuleFailure] = Field(default_factory=list)
    stuck: list[StuckModule] = Field(default_factory=list)
    drift: list[Drift] = Field(default_factory=list)
    gnss_outage: list[GnssOutage] = Field(default_factory=list)
    process_kill: list[ProcessKill] = Field(default_factory=list)
    # None (no [faults.uwb] table) = the gaussian model; kept out of to_dict() then, so configs
    # written before this field existed hash and simulate exactly as before
    uwb: UwbErrorModel | None = None

    @model_validator(mode="after")
    def _windows(self) -> "Faults":
        if self.uwb is not None and self.uwb.model == "realistic" and self.interference.enabled:
            raise ValueError("uwb.model = 'realistic' replaces the interference fault: set "
                             "[faults.interference] enabled = false")
        for name in ("module_failure", "stuck", "drift", "gnss_outage"):
            for i, w in enumerate(getattr(self, name)):
                if w.end_s <= w.start_s:
                    raise ValueError(f"{name}[{i}]: end_s {w.end_s} must be after start_s {w.start_s}")
        for i, k in enumerate(self.process_kill):
            if k.restart_s is not None and k.restart_s <= k.at_s:
                raise ValueError(f"process_kill[{i}]: restart_s must be after at_s")
        return self


class InitialKnowledge(_Model):
    """Coarse-alignment errors of every estimator's initial state (position sigma = its GNSS)."""

    vel_sigma_mps: NonNegFloat = 0.1
    roll_pitch_sigma_deg: NonNegFloat = 0.5
    yaw_sigma_deg: NonNegFloat = 2.0


class Estimation(_Model):
    """Settings shared by the estimators (tuning, not scenario truth)."""

    rounds: int = Field(3, ge=1, le=100, description="max message-iteration rounds per epoch")
    convergence_m: NonNegFloat = 0.01  # swarm-wide: stop when every node moved less than this
    fixed_lag_s: PositiveFloat = 5.0
    delta_l_file: str = "configs/delta_l.json"  # written by `swarmnav calibrate`
    delta_l_fallback_sigmas: PositiveFloat = 3.0  # Δl = this × UWB sigma when no training exists
    residual_window_epochs: int = Field(1, ge=1)  # K-means over a sliding window (sparse real data)
    peer_timeout_s: PositiveFloat = 2.0  # distributed: wall-clock wait for a live peer's round state
    # optional estimator tuning overrides (estimators/settings.py EstimatorTuning, e.g. commit_weight);
    # None = the estimators' documented defaults
    graph: dict[str, float | int | bool | str | list | dict | None] | None = None

    @field_validator("graph")
    @classmethod
    def _check_tuning(cls, v):
        from .estimators.settings import validate_tuning

        validate_tuning(v)  # a typo'd key fails naming it
        return v


def estimation_values(settings: Mapping | None) -> Estimation:
    """The typed ``[estimation]`` values of an estimator settings dict (``registry.estimator_settings``:
    this table's ``model_dump()`` plus ``delta_l_m``, ...): the fields the dict sets, validated, and
    :class:`Estimation`'s defaults for the others. Every reader of ``rounds``, ``convergence_m``,
    ``fixed_lag_s``, ``residual_window_epochs``, ``delta_l_fallback_sigmas`` or ``peer_timeout_s``
    goes through it, so their defaults are the fields above and nowhere else."""
    s = settings or {}
    return Estimation.model_validate({k: s[k] for k in Estimation.model_fields if k in s})


MAX_SEEDS = 100_000  # per range of a seed list (a Monte Carlo runs 10)


def parse_seed_spec(spec: str | int | list[int]) -> list[int]:
    """Seeds from ``"1-10"``, ``"1,3,7"``, mixes like ``"1-3,7"``, one int, or a list of ints: sorted,
    duplicates removed. Raises ValueError naming the bad part."""
    if isinstance(spec, bool):
        raise ValueError(f"not a seed list: {spec!r}")
    if isinstance(spec, int):
        spec = [spec]
    out: set[int] = set()
    if isinstance(spec, list):
        out.update(int(s) for s in spec)
    else:
        for part in str(spec).replace(" ", "").split(","):
            if not part:
                continue
            try:
                if "-" in part[1:]:
                    i = part.index("-", 1)
                    lo, hi = int(part[:i]), int(part[i + 1:])
                    if hi < lo:
                        raise ValueError
                    if hi - lo >= MAX_SEEDS:  # "1-100000000" built a set of 1e8 ints (GBs) before any check
                        raise OverflowError
                    out.update(range(lo, hi + 1))
                else:
                    out.add(int(part))
            except ValueError:
                raise ValueError(f"cannot parse seeds {part!r} (use e.g. 1-5, 1,3,7 or 1-3,7)") from None
            except OverflowError:
                raise ValueError(f"seeds {part!r}: more than {MAX_SEEDS} in one range; give fewer") from None
    if not out:
        raise ValueError("no seed given")
    if min(out) < 0:
        raise ValueError("seeds must be >= 0")
    return sorted(out)


class Evaluation(_Model):
    """Which seeds tune and which report (``[evaluation]``): tune nothing to a seed you report.

    Settings (``[estimation]``, Δl training) are chosen on ``tuning_seeds`` of this scenario and on
    the scenarios named in ``tuning_scenarios``; the headline (README, docs/results.md) is a Monte
    Carlo over ``report_seeds`` (``swarmnav evaluate --seeds report``). The two sets are disjoint."""

    tuning_seeds: str | list[int] = Field("1001-1010", description="seeds the settings were tuned on, e.g. '1001-1010'")
    report_seeds: str | list[int] = Field("1-10", description="seeds the headline is reported on, e.g. '1-10'")
    tuning_scenarios: list[str] = Field(default_factory=list,
                                        description="other scenarios (config names) the settings were tuned on")

    @model_validator(mode="after")
    def _disjoint(self) -> "Evaluation":
        tune, rep = self.seeds("tuning"), self.seeds("report")  # raise on a bad spec
        both = sorted(set(tune) & set(rep))
        if both:
            raise ValueError(f"tuning_seeds and report_seeds overlap on {both}: tune nothing to a seed you report")
        return self

    def seeds(self, role: Literal["tuning", "report"]) -> list[int]:
        return parse_seed_spec(self.tuning_seeds if role == "tuning" else self.report_seeds)

    def role_of(self, seeds) -> str:
        """'report', 'tuning', 'mixed' (some of each: numbers not to publish) or 'other'."""
        s = {int(x) for x in seeds}
        tune, rep = set(self.seeds("tuning")), set(self.seeds("report"))
        if not s:
            return "other"
        if s <= tune:
            return "tuning"
        return "mixed" if s & tune else "report" if s <= rep else "other"


def evaluation_block(table: dict | None, seeds) -> dict | None:
    """report.json ``evaluation``: the scenario's named tuning and report seeds and what ``seeds`` are
    ('report', 'tuning', 'mixed' or 'other'); None when the data names none (e.g. a recording)."""
    if not table:
        return None
    ev = Evaluation.model_validate(table)
    return {"tuning_seeds": ev.seeds("tuning"), "report_seeds": ev.seeds("report"),
            "tuning_scenarios": list(ev.tuning_scenarios), "seeds_role": ev.role_of(seeds)}


class Scenario(_Model):
    """A whole scenario file."""

    scenario: ScenarioMeta
    origin: Origin
    swarm: Swarm
    trajectory: Trajectory = Trajectory()
    sensors: Sensors
    faults: Faults = Faults()
    init: InitialKnowledge = InitialKnowledge()
    estimation: Estimation = Estimation()
    evaluation: Evaluation = Evaluation()

    @model_validator(mode="after")
    def _cross(self) -> "Scenario":
        n = self.swarm.n_uavs
        for f in self.faults.module_failure + self.faults.stuck + self.faults.process_kill:
            if f.uav > n:
                raise ValueError(f"faults: uav {f.uav} does not exist (n_uavs = {n})")
        for d in self.faults.drift:
            if not all(1 <= u <= n for u in d.link) or d.link[0] == d.link[1]:
                raise ValueError(f"faults.drift: link {d.link} is not a pair of distinct UAVs in 1..{n}")
        for i, o in enumerate(self.faults.gnss_outage):
            bad = [u for u in o.uavs if not 1 <= u <= n] if isinstance(o.uavs, list) else []
            if bad:
                raise ValueError(f"faults.gnss_outage[{i}]: uavs {bad} are not UAV ids in 1..{n} "
                                 "(or use \"slaves\", \"masters\" or \"all\")")
        return self

    def uav_ids(self) -> list[int]:
        return list(range(1, self.swarm.n_uavs + 1))

    def faults_after_end(self) -> list[str]:
        """The fault windows that start at or after the scenario's end, so never happen (e.g.
        paper.toml's with ``--set scenario.duration_s=60``), each as 'faults.<kind>[i] (start-end s)'."""
        T = self.scenario.duration_s
        return [f"faults.{name}[{i}] ({w.start_s:g}-{w.end_s:g} s)"
                for name in ("module_failure", "stuck", "drift", "gnss_outage")
                for i, w in enumerate(getattr(self.faults, name)) if w.start_s >= T]

    def to_dict(self) -> dict:
        d = self.model_dump(mode="json")
        if d["faults"].get("uwb") is None:  # no [faults.uwb]: the dict (and sha256) of older configs
            d["faults"].pop("uwb", None)
        for k in ("masters_every", "density_per_km3"):  # the scale family's options, when unset
            if d["swarm"].get(k) is None:
                d["swarm"].pop(k, None)
        return d

    def sha256(self) -> str:
        return hashlib.sha256(json.dumps(self.to_dict(), sort_keys=True).encode()).hexdigest()
