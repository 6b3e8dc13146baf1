"""What to record next: predicted ``T_ds`` accuracy over an operating range (:mod:`.predict`) and the
next best snapshots (:mod:`.plan`); ``--range`` / ``--tolerance`` parsing in :mod:`.range_spec`."""
