"""``dcc-fg batch STUDY.yaml``: sweeps of VIO runs on Dask, evaluated and gathered into one table.

A study file lists recordings (or simulated flights with their seeds), the VIO modes to run on each
and their options. Every run and mode is one task on a ``dask.distributed`` cluster (a local one of
single-threaded worker processes by default, or an existing one with ``--scheduler``), is evaluated
against its ground truth and becomes one row of ``OUT/results.csv``, ``OUT/results.md`` (the paper's
Tables IV-V) and ``OUT/results_rmse.png``. A failed run is a row with its error; the others go on.
A finished run is not redone when the study is run again (``--force`` redoes it).

Study file schema (YAML; paths relative to the study file's folder)::

    out: study_out              # output folder (optional; --out overrides it)
    defaults:                   # optional: what every run gets unless it sets the key itself
      modes: [dcc, scc, mono]
      options: {keyframe_every: 3}
      vio: {run: {pixel_sigma: 1.0}}
    runs:
      - name: flight-a          # letters, digits, '_', '.', '-'; unique (per mode)
        simulate:               # a simulated flight (dcc-fg simulate flight), with its ground truth
          kind: flight          # the only kind
          duration: 20          # s (> 4; a short loop needs >= ~8 s to stay below 30 m/s)
          pattern: short        # short: one 16 m x 8 m loop; loops: the paper's two 30 m x 15 m loops
          seed: 1               # or a list [1, 2, 3]: one run per seed, named flight-a-seed1, ...
          scale: 1.0            # image resolution relative to 640x480, within [0.1, 2]
          gimbal: moving        # moving | locked (scc runs always fly the flight with the gimbal locked)
          format: ros2          # ros1 | ros2
          noise: 2.0            # image noise, grey levels (1 sigma)
        modes: [dcc, scc, mono]
        options: {keyframe_every: 3, lag: 1.5}   # smoother fields (VioOptions) except mode and sigma
        vio:                    # the other sections of dcc-fg vio's --config (dcc-fg config --print vio)
          run: {pixel_sigma: 1.0, frontend_worker: inline}
          topics: {imu: /imu0}
          frontend: {}
          output: {accept_unhealthy: false}
      - name: field-test
        bag: data/flight.bag    # a recording instead (ROS1 .bag or ROS2 folder)
        calibration: data/calibration.yaml      # with an imu: section, or give imu_yaml + camchain
        ground_truth: data/gt.tum               # TUM (body frame) or a bag with /ground_truth/pose
        imu_yaml: data/imu.yaml                 # optional (Kalibr)
        camchain: data/camchain-imucam.yaml     # optional (Kalibr, cam0.T_cam_imu)
        modes: [dcc]

A run's ``options``/``vio`` are laid over ``defaults`` key by key (a ``vio`` section as a whole). An
``scc`` run holds the joints at ``options.theta_fixed`` (rad), else at a simulated flight's locked
mid position, else at the calibration's ``flight.joints_locked``. The front end runs inline by
default (``vio.run.frontend_worker``): the cores go to parallel runs.

The whole file is validated before any run starts (unknown keys, wrong types, unknown modes,
repeated names, missing files, invalid VIO options): a ``ConfigError`` naming the file and the field
(exit code 2). Bags are not opened then: a corrupt bag is a failed run.

Output folder::

    OUT/results.csv, results.md, results_rmse.png    the table (written together, replaced each time)
    OUT/runs/NAME-MODE-HASH/    dcc-fg vio outputs, evaluation.json, result.json (the row; marks it finished)
    OUT/data/flight-sSEED-GIMBAL-HASH/              simulated flights (dcc-fg simulate flight), reused
    OUT/logs/NAME-MODE-HASH.log                      each run's log, tracebacks of failures included

``HASH`` is a stable hash of the run's spec (the flight's settings or the input files' paths, sizes
and times; the mode; every effective VIO option), so an edited run gets a new folder and the old
result is not mistaken for it.

From Python: ``run_study(load_study("study.yaml"), BatchOptions(Path("out"), workers=2))`` returns the
rows and the timing (:class:`BatchResult`). The local cluster's workers are *spawned* processes, so a
script that calls it must guard its entry point with ``if __name__ == "__main__":`` (the ``dcc-fg``
command and pytest do).

Modules: :mod:`~dcc_fg.batch.study` (schema, validation, tasks), :mod:`~dcc_fg.batch.tasks` (what a
worker runs), :mod:`~dcc_fg.batch.runner` (Dask), :mod:`~dcc_fg.batch.table` (CSV, Markdown, figure).
"""

from dcc_fg.batch.runner import BatchOptions, BatchResult, run_study
from dcc_fg.batch.study import Study, load_study

__all__ = ["BatchOptions", "BatchResult", "Study", "load_study", "run_study"]
