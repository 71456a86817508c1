"""Many logs at once, on Ray: ``driftmap batch`` (docs/fleet.md).

One concept per module: :mod:`~driftmap.fleet.inputs` (paths, globs and list files -> one :class:`LogSpec` per
log), :mod:`~driftmap.fleet.config` (the ``[fleet]`` table and the config hash ``--resume`` checks),
:mod:`~driftmap.fleet.folders` (the output folder; logs appear whole or not at all), :mod:`~driftmap.fleet.task`
(one log: build -> diagnose -> exports), :mod:`~driftmap.fleet.runner` (Ray: embedded or a cluster, retries,
``--resume``, Ctrl-C), :mod:`~driftmap.fleet.report` (``fleet.json``, ``fleet.html``) and
:mod:`~driftmap.fleet.synth` (a fleet of synthetic logs, ``driftmap synth --fleet``).

Ray is an optional dependency (``pip install 'driftmap[fleet]'``): it is imported only when a batch runs.
"""

from driftmap.fleet.config import BatchConfig, FleetSettings, config_hash, load_batch_config
from driftmap.fleet.inputs import LogSpec, expand_inputs
from driftmap.fleet.report import CONTRACT_KEYS
from driftmap.fleet.runner import FleetProgress, FleetResult, plan_workers, require_ray, run_batch
from driftmap.fleet.synth import FleetLog, synth_fleet
from driftmap.fleet.task import run_log

__all__ = ["CONTRACT_KEYS", "BatchConfig", "FleetLog", "FleetProgress", "FleetResult", "FleetSettings", "LogSpec",
           "config_hash", "expand_inputs", "load_batch_config", "plan_workers", "require_ray", "run_batch", "run_log",
           "synth_fleet"]
