"""swarmnav — cooperative navigation for UAV swarms (ATVFG, Wang, Hu & Tao 2025).

The ``swarmnav`` package is the pure core: simulation, estimators, detection and metrics.
It does no I/O beyond explicit dataset/config (de)serialisation helpers and never imports
zenoh or rerun; the adapters that do live in ``services/``.

Frames: ENU local-level about the geodetic origin (metres), body frame FLU. Time: seconds
of simulation time from the start of the run.
"""

__version__ = "0.1.0"
