"""Typed estimator tuning: the keys a scenario's ``[estimation.graph]`` table may set.

One model, :class:`EstimatorTuning`, lists every tuning key the estimators read (graph.py: atvfg,
atvfg_paper, fg, ins; central.py; fkf.py; imu.py's rest detector), with its default, unit and
meaning. The config loader validates ``[estimation.graph]`` against it (``extra="forbid"``), so a
typo fails naming the key instead of being silently ignored. Every estimator reads its tuning
through :func:`tuning` (this model: the defaults are here and only here; tests/test_settings.py
holds every key the estimators read to this list).

Units: metres (m), seconds (s), m/s, radians unless a name says otherwise; "factor" = multiple of
the quantity named; "scale" = multiplies a σ.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

# the defaults of detection.py and factors.py, repeated here so that loading a config never imports
# gtsam (tests/test_settings.py holds them equal)
DEFAULT_FLOOR_FACTOR = 3.0
DEFAULT_CEIL_FACTOR = 10.0
DRAG_SIGMA_SCALE = 1.5


class EstimatorTuning(BaseModel):
    """Every estimator tuning key, with its default (docs/estimators.md explains each in context)."""

    model_config = ConfigDict(extra="forbid")

    # -- detection (atvfg, atvfg_paper) --------------------------------------------------------
    delta_h_floor_factor: float = Field(DEFAULT_FLOOR_FACTOR, gt=0, description="Δh never below this × Δl")
    delta_h_ceil_factor: float | None = Field(DEFAULT_CEIL_FACTOR, description="2-means descent ceiling, × Δl (≤ 0 or None: none)")
    h1_weight_cap: bool = Field(True, description="cap eq. 24's H1 weight at (Δl/∂)²")
    kmeans_backend: Literal["exact", "sklearn"] = Field("exact", description="2-means solver for Δh")
    delta_l_sigma_tolerance: float = Field(0.1, ge=0, description="relative ranging-σ mismatch up to which a trained Δl applies")
    residual_window_min: int = Field(16, ge=1, description="adaptive K-means pool: at least this many residuals")
    residual_window_max_epochs: int = Field(30, ge=1, description="adaptive K-means pool: at most this many epochs (epochs)")
    # -- cooperative measurements ---------------------------------------------------------------
    use_azel: bool = Field(True, description="use relative azimuth/elevation (eq. 26-27)")
    azel_weight: Literal["full", "range"] = Field("full", description="az/el weight: full, or the range link's class weight")
    reverse_azel: Literal["rounds", "commit", "off"] = Field("rounds", description="use the neighbours' az/el of this node")
    peer_levers: bool = Field(True, description="use the peers' tag lever arms (needs their attitude)")
    gn_iterations: int = Field(2, ge=1, description="Gauss-Newton iterations per round solve")
    # -- double counting and what is reported (graph.py docstring, docs/estimators.md) -----------
    neighbour_cov_inflation: float | Literal["links"] = Field("links", description="neighbour covariance inflation at commit (× or per-sender link count)")
    neighbourhood_radius_m: float | None = Field(None, gt=0, description="a node reads the ranges of, and solves with, the UAVs it measured or that measured it, those within this distance of it (m), and the other ends of their ranges (None: every live UAV, the whole swarm)")
    round_cov_inflation: float | None = Field(0.5, description="neighbour covariance × this in the round solves (None: as at commit)")
    round_solver: Literal["own", "joint"] = Field("own", description="the rounds: \"own\" = each node solves its own position against its neighbours' current ones (block Jacobi, ~9 rounds); \"joint\" = round 1 solves the neighbourhood's joint snapshot from the round-0 priors (joint.py), so rounds = 1 suffices")
    joint_irls_passes: int = Field(2, ge=0, description="round_solver \"joint\": re-weighting passes of the double-threshold test (weights at the priors, then at each solution)")
    round_warm_start: bool = Field(False, description="start an epoch's rounds (and its round-0 broadcast) at the prior plus the last epoch's cooperative correction (round solution − smoother after the commit, m), near their fixed point; the solve's prior is unchanged")
    range_memory_epochs: int = Field(0, ge=0, description="range memory: the clean (H2) ranges of this many past epochs, moved to the epoch by the two UAVs' velocity-integrated displacements (transport variance estimated online from the node's own ranges), as extra range rows (weight 1 − commit_weight) of the reported solve; rounds, broadcasts and commit unchanged (0: off; range_memory.py)")
    commit_weight: float = Field(0.3, ge=0, le=1, description="weight of the cooperative information committed to the smoother")
    commit_update: Literal["epoch_end", "next_epoch"] = Field("epoch_end", description="when the commit's factor enters the smoother: its own ISAM2 update at the epoch's end, or the next epoch's update with that epoch's own factors (one update per epoch instead of two; the velocity and attitude reported for an epoch are then the smoother's before its commit)")
    report: Literal["round", "belief", "smoother"] = Field("round", description="the estimate reported: the last round's solution (with its sandwich covariance), the belief, or the smoother's")
    # -- smoother -------------------------------------------------------------------------------
    relinearize_threshold: float = Field(0.05, gt=0, description="ISAM2 relinearisation threshold (rad, m, m/s, bias units)")
    bias_rw_floor: tuple[float, float] = Field((1e-5, 1e-4), description="bias random-walk floors (rad/s/√s, m/s²/√s)")
    # -- GNSS -----------------------------------------------------------------------------------
    gnss_sigma_scale: float = Field(2.5, gt=0, description="GNSS position σ × this (correlated Gauss-Markov errors)")
    gnss_sigma_scale_by_role: dict[str, float] = Field(default_factory=dict, description="per role (master/slave) override of gnss_sigma_scale")
    gnss_extra_var_m2: float = Field(0.0, ge=0, description="extra GNSS position variance (m²)")
    # -- rotor drag (multirotors) ---------------------------------------------------------------
    rotor_drag: bool = Field(True, description="rotor-drag velocity factor on multirotors")
    drag_mu_prior: float = Field(0.5, description="prior mean of the drag coefficient (1/s)")
    drag_mu_prior_sigma: float = Field(0.5, gt=0, description="its prior σ (1/s)")
    drag_sigma_scale: float = Field(DRAG_SIGMA_SCALE, gt=0, description="drag factor σ × this")
    # -- anchors and passive ranging (real data) ------------------------------------------------
    anchor_time_shift: bool = Field(True, description="move an anchor range to the epoch by the UAV's velocity")
    anchor_kernel: Literal["huber", "cauchy", "tukey", "gm"] = Field("huber", description="robust kernel of anchor ranges")
    anchor_kernel_k: float = Field(3.0, gt=0, description="its threshold (σ)")
    use_tdoa: bool = Field(True, description="use passive-listening range differences")
    tdoa_detection: bool = Field(False, description="run the double-threshold test on them")
    tdoa_sigma_scale: float = Field(1.0, gt=0, description="their σ × this")
    tdoa_offset_m: float = Field(0.0, description="offset subtracted from each (m)")
    relink_s: float = Field(0.0, ge=0, description="relink window of the commit (s; 0: off)")
    relink_weight: float = Field(0.3, ge=0, le=1, description="weight of the relinked information")
    relink_cov_scale: float = Field(0.5, gt=0, description="neighbour covariance × this in the relink")
    relink_tdoa_detection: bool = Field(True, description="detection on the relinked passive rows")
    relink_tdoa_delta_l: float | None = Field(None, description="their Δl (× σ; None: delta_l_fallback_sigmas)")
    relink_tdoa_sigma: Literal["innovation", "nominal"] = Field("innovation", description="their σ")
    # -- initial rest detector (imu.py) ---------------------------------------------------------
    initial_rest_zupt: bool = Field(True, description="zero-velocity prior while a UAV that started at rest is still")
    rest_max_speed_mps: float = Field(0.1, gt=0, description="rest: speed bound (m/s)")
    rest_accel_std: float = Field(0.1, gt=0, description="rest: accelerometer std bound (m/s²)")
    rest_gyro_std: float = Field(0.01, gt=0, description="rest: gyro std bound (rad/s)")
    zupt_sigma_mps: float = Field(0.02, gt=0, description="zero-velocity prior σ (m/s)")
    # -- central (oracle) -----------------------------------------------------------------------
    central_lag_s: float = Field(1.5, gt=0, description="its fixed lag (s)")
    central_use_rel: bool = Field(True, description="use az/el")
    central_covariance: bool = Field(True, description="extract marginal covariances")
    central_gyro_rw_floor: float = Field(3e-5, gt=0, description="gyro bias random-walk floor (rad/s/√s)")
    central_accel_rw_floor: float = Field(3e-4, gt=0, description="accelerometer bias random-walk floor (m/s²/√s)")
    central_integration_sigma: float = Field(1e-3, gt=0, description="preintegration integration σ")
    central_relin_threshold: float = Field(0.05, gt=0, description="ISAM2 relinearisation threshold")
    central_relin_skip: int = Field(1, ge=1, description="ISAM2 relinearise every this many updates")
    central_factorization: Literal["CHOLESKY", "QR"] = Field("CHOLESKY", description="ISAM2 factorization (where Cholesky refuses the graph, the oracle switches to QR by itself)")
    central_first_epoch_iterations: int = Field(0, ge=0, le=100, description="extra ISAM2 iterations of the first epoch (until no UAV moves 1 cm; 0: one Gauss-Newton step per epoch, as the nodes' smoothers)")
    # -- fkf ------------------------------------------------------------------------------------
    fkf_beta_master: float = Field(0.0, ge=0, le=1, description="information-sharing factor of the master filter")
    fkf_beta_gnss: float = Field(0.5, ge=0, le=1, description="... of the GNSS sub-filter")
    fkf_beta_uwb: float = Field(0.5, ge=0, le=1, description="... of the UWB sub-filter")
    fkf_chi2_p: float = Field(0.999, gt=0, lt=1, description="chi-square isolation probability")
    fkf_isolation: Literal["measurement", "subfilter"] = Field("measurement", description="what the χ² test isolates")
    fkf_gnss_isolation: bool = Field(False, description="χ² isolation of GNSS too")
    fkf_neighbour_cov_scale: float = Field(1.0, gt=0, description="neighbour covariance × this")
    fkf_neighbour_fusion: Literal["ci", "independent"] = Field("ci", description="neighbour fusion: covariance intersection or as independent")
    fkf_neighbour_corr: Literal["split", "none"] = Field("split", description="correlation model of neighbour estimates")
    fkf_anchor_max_reject: int = Field(3, ge=0, description="consecutive anchor rejections before reset")

    @model_validator(mode="after")
    def _joint_needs_round0_priors(self):
        # the joint snapshot takes each node's round-0 position as its epoch prior mean, which the
        # warm start shifts by the last correction
        if self.round_solver == "joint" and self.round_warm_start:
            raise ValueError("round_solver = \"joint\" solves from the round-0 priors: set round_warm_start = false")
        if self.commit_update == "next_epoch" and self.report == "smoother":
            raise ValueError("report = \"smoother\" reports the smoother after the commit: set commit_update = \"epoch_end\"")
        if self.commit_update == "next_epoch" and self.round_warm_start:
            raise ValueError("round_warm_start carries the correction past the committed smoother: set commit_update = \"epoch_end\"")
        if self.commit_update == "next_epoch" and (self.relink_s > 0 or self.commit_weight == 0):
            raise ValueError("commit_update = \"next_epoch\" has nothing to defer with relink_s > 0 (the relinked "
                             "commit updates the smoother itself) or commit_weight = 0 (no commit): remove it")
        return self


def tuning(settings: dict | None) -> EstimatorTuning:
    """The typed tuning of an estimator's settings dict: its tuning keys (the top level with the
    ``[estimation.graph]`` table, ``settings["graph"]``, merged over it) validated, every other
    field at its default. Keys that are not tuning keys (the ``[estimation]`` table's own: rounds,
    fixed_lag_s, delta_l_m, ...) are left to their readers."""
    s = dict(settings or {})
    s.update(s.get("graph") or {})
    return EstimatorTuning.model_validate({k: v for k, v in s.items() if k in EstimatorTuning.model_fields})


def validate_tuning(table: dict | None) -> dict:
    """``[estimation.graph]`` checked against :class:`EstimatorTuning`; returns the table as given
    (only the keys set, so the estimators' defaults apply to the others). Raises ValueError naming
    the first bad key: an unknown one (with the closest known key) or a value out of range."""
    if not table:
        return {}
    try:
        EstimatorTuning.model_validate(table)
    except ValidationError as e:
        err = e.errors()[0]
        key = ".".join(str(x) for x in err["loc"]) or "?"
        if err["type"] == "extra_forbidden":
            import difflib  # only to name the closest key (every UAV process validates its tuning)

            near = difflib.get_close_matches(key, list(EstimatorTuning.model_fields), n=1)
            hint = f"did you mean {near[0]!r}? " if near else ""
            raise ValueError(f"unknown tuning key {key!r}: {hint}the keys are listed in docs/settings.md") from None
        msg = err["msg"].removeprefix("Value error, ")
        raise ValueError(f"{key}: {msg}" if err["loc"] else msg) from None
    return dict(table)


def settings_table_markdown() -> str:
    """docs/settings.md: the table of every tuning key, generated from :class:`EstimatorTuning`
    (tests/test_settings.py holds the file equal to this)."""
    rows = ["# Estimator tuning keys (`[estimation.graph]`)", "",
            "Generated from `shared/swarmnav/estimators/settings.py` (`EstimatorTuning`); a key not listed here is",
            "refused when the config loads. docs/estimators.md explains the methods behind them.", "",
            "| key | default | meaning |", "|---|---|---|"]
    for name, f in EstimatorTuning.model_fields.items():
        d = f.get_default(call_default_factory=True)
        rows.append(f"| `{name}` | `{d!r}` | {f.description or ''} |")
    return "\n".join(rows) + "\n"
