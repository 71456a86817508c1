"""Map-consistency diagnostics (double walls, smearing, drift attribution).

One module per concept, from the bottom up: ``noise`` (sensor noise along a normal), ``samples`` (per-frame
samples with own-frame normals, placed with a revision's poses), ``surfaces`` (surface groups and lateral cells),
``layers`` (the per-voxel two-layer test and smearing), ``wall_results`` (the detector's config and result types),
``detector`` (all voxel sizes, regions), ``entropy`` (MME / MPV), ``attribution`` (per-frame disagreement, change
points, drift rate), ``coverage``, ``causes``, ``verify``, ``ground_truth``, ``diagnose_config``, ``diagnosis`` (the
run: :func:`~driftmap.diagnostics.diagnosis.diagnose_store`) and ``figures``. ``double_wall`` and ``report`` are
front doors re-exporting the names they always had. Voxel keys come from :mod:`driftmap.voxels`.
"""
