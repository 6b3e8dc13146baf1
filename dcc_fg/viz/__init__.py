"""Interactive visualization of calibration, validation and VIO runs (``--rerun FILE.rrd``, ``--rerun-spawn``).

:mod:`.rerun_log` is the only module that uses ``rerun-sdk`` (the optional extra ``dcc-fg[viz]``);
:mod:`.scene` and :mod:`.vio_scene` compute what is shown (frames, reprojections, the ground truth in the
estimate's world), :mod:`.images` reads a calibration's images again for display. Layer: report / plots /
export (``tests/test_layering.py``).
"""
