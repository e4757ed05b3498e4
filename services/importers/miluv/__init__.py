"""MILUV recording -> swarmnav dataset (``swarmnav import-miluv``). See ``docs/miluv.md``.

Reads one MILUV experiment folder (``ifo00N/*.csv`` plus ``config/``) and builds a
:class:`swarmnav.dataset.Dataset`, one module per part:

- ``readers``: CSV (csv module + numpy), YAML config (PyYAML), vectors, time-series cleaning;
- ``nodes``: UAV ``N`` for robot ``ifo00N`` (tags and lever arms from ``config/uwb/tags.yaml``) and one
  static node ``100 + k`` per UWB anchor ``k`` (kind "anchor", position from
  ``config/uwb/anchors.yaml`` for the experiment's constellation; tag id = anchor id, zero lever arm);
  frame: the Vicon world frame (z up) is used as the local frame, x -> E, y -> N, z -> U; no geodetic
  origin, no GNSS;
- ``series``: per-robot mocap (attitude glitches bridged), IMU, rangefinder; the common time span;
- ``tables``: IMU (``imu_px4.csv``, mavros ``data_raw``, already ROS body FLU, every sample kept,
  variable rate), altitude (``height.csv`` minus the per-robot bias, readings at the sensor floor
  dropped), the at-rest test for coarse alignment;
- ``truth``: mocap resampled to a 10-sub-step grid of the epochs (velocities by central differences,
  attitudes by ``scipy.spatial.transform.Slerp``) and true tag positions for the error labels;
- ``ranges``: ``uwb_range.csv`` of all robots, deduplicated on (timestamp, unordered tag pair),
  sigma = the row's ``std``, labels from ``bias``/``std``;
- ``passive``: ``uwb_passive.csv`` of all robots (a third tag overhearing a two-way ranging
  transaction) turned into range differences with the transaction's own timestamps
  (``passive_rdiff``), deduplicated on (listener, initiator, responder, transaction time), labels
  from mocap;
- ``importer``: :func:`convert`, which runs them in order and assembles the metadata.

Everything computes in memory; :func:`convert` returns the dataset and a summary dict.
"""

from .constants import ANCHOR_NODE_OFFSET
from .importer import DEFAULT_ESTIMATION, convert
from .passive import passive_rdiff
from .readers import parse_vector, read_csv, read_yaml

__all__ = ["ANCHOR_NODE_OFFSET", "DEFAULT_ESTIMATION", "convert", "parse_vector", "passive_rdiff", "read_csv", "read_yaml"]
