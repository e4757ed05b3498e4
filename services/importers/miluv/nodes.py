"""The experiment's nodes from ``config/``: UAV ``N`` per robot ``ifo00N`` (UWB tags and lever arms
from ``uwb/tags.yaml``, IMU noise from ``imu/ifo00N/px4_imu.yaml``) and a static node ``100 + k``
per UWB anchor ``k`` of the experiment's constellation (``uwb/anchors.yaml``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from swarmnav.dataset import ImuNoise, Node
from swarmnav.errors import DatasetError

from .constants import ACCEL_BIAS_SIGMA, ANCHOR_NODE_OFFSET, GYRO_BIAS_SIGMA
from .readers import nonneg_float, parse_vector, read_yaml


@dataclass
class Layout:
    """Who is who: the dataset's nodes and the UWB ids that belong to them."""

    nodes: list[Node]  # UAVs in robot order, then anchors by id
    anchors: dict[int, tuple[float, float, float]]  # MILUV anchor id -> Vicon-frame position [m]
    tag_owner: dict[int, int]  # UWB tag/anchor id -> node id
    imu_noise: dict[int, ImuNoise]  # UAV id -> its IMU noise (the same object its Node holds)
    height_bias: dict  # robot name -> rangefinder bias (config/height/bias.yaml, unparsed)
    absent_tags: dict[int, str] = field(default_factory=dict)  # tag id -> robot of tags.yaml without a folder here

    def levers(self) -> dict[int, dict[int, tuple[float, float, float]]]:
        """node id -> {tag id: lever arm in the body frame [m]}."""
        return {n.id: n.tags for n in self.nodes}


def read_layout(cfg: Path, exp_name: str, robots: list[tuple[str, int]], constellation: str,
                used_files: list[Path]) -> Layout:
    """Nodes, anchors and tag ownership of the experiment (``cfg``: MILUV's config/ folder); appends
    the files read to ``used_files``."""
    anchors_cfg = read_yaml(cfg / "uwb" / "anchors.yaml")
    tags_cfg = read_yaml(cfg / "uwb" / "tags.yaml")
    hbias_cfg = read_yaml(cfg / "height" / "bias.yaml")
    used_files += [cfg / "uwb" / "anchors.yaml", cfg / "uwb" / "tags.yaml", cfg / "height" / "bias.yaml"]
    if not isinstance(anchors_cfg.get(constellation), dict):
        raise DatasetError(f"{cfg / 'uwb' / 'anchors.yaml'}: no constellation {constellation!r} (experiment {exp_name}'s "
                           f"anchor_constellation in experiments.csv; the file has {sorted(anchors_cfg)})")
    anchors = {_int_key(k, cfg / "uwb" / "anchors.yaml"): parse_vector(v, 3, f"anchors.yaml[{constellation}][{k}]")
               for k, v in anchors_cfg[constellation].items()}
    tag_owner: dict[int, int] = {}
    nodes: list[Node] = []
    imu_noise: dict[int, ImuNoise] = {}
    for name, uid in robots:
        tcfg = tags_cfg.get(name)
        if not isinstance(tcfg, dict) or not tcfg:
            raise DatasetError(f"{cfg / 'uwb' / 'tags.yaml'}: no tags for {name} (the file has {sorted(tags_cfg)})")
        tags = {_int_key(k, cfg / "uwb" / "tags.yaml"): parse_vector(v, 3, f"tags.yaml[{name}][{k}]") for k, v in tcfg.items()}
        for tg in tags:
            if tg in anchors or tg in tag_owner:
                raise DatasetError(f"tag id {tg} of {name} is not unique (anchor or other robot)")
            tag_owner[tg] = uid
        ip = cfg / "imu" / name / "px4_imu.yaml"
        used_files.append(ip)
        imu_noise[uid] = _imu_noise(read_yaml(ip), str(ip))
        # the ifo robots are quadrotors (MILUV paper): declared so the rotor-drag model can apply
        nodes.append(Node(id=uid, kind="uav", role="slave", tags=tags, imu=imu_noise[uid], airframe="multirotor"))
    absent: dict[int, str] = {}
    present = {name for name, _ in robots}
    for name, tcfg in tags_cfg.items():
        if name not in present and isinstance(tcfg, dict):
            for k in tcfg:
                try:
                    absent[int(k)] = name
                except ValueError:
                    continue
    for k, pos in sorted(anchors.items()):
        nodes.append(Node(id=ANCHOR_NODE_OFFSET + k, kind="anchor", role="anchor", position_enu=pos, tags={k: (0.0, 0.0, 0.0)}))
        tag_owner[k] = ANCHOR_NODE_OFFSET + k
    return Layout(nodes, anchors, tag_owner, imu_noise, hbias_cfg,
                  {t: r for t, r in absent.items() if t not in tag_owner})


def _int_key(k: str, where: Path) -> int:
    try:
        return int(k)
    except ValueError:
        raise DatasetError(f"{where}: UWB id {k!r} is not an integer") from None


def _imu_noise(ic: dict, where: str) -> ImuNoise:
    # Kalibr/Allan convention: noise densities [unit/sqrt(Hz)], random walks [unit/s/sqrt(Hz)] = SI as ImuNoise wants
    return ImuNoise(
        gyro_noise_density=nonneg_float(ic, "gyroscope_noise_density", where),
        accel_noise_density=nonneg_float(ic, "accelerometer_noise_density", where),
        gyro_bias_sigma=GYRO_BIAS_SIGMA,
        accel_bias_sigma=ACCEL_BIAS_SIGMA,
        gyro_bias_rw=nonneg_float(ic, "gyroscope_random_walk", where),
        accel_bias_rw=nonneg_float(ic, "accelerometer_random_walk", where),
    )
