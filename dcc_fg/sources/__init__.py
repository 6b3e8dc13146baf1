"""Recordings -> measurements: readers that turn bags, folders and files into dcc-fg's domain types.

Each reader here parses its format through :mod:`dcc_fg.io` (files and bags as arrays and plain
dicts) and assembles the measurements (:mod:`dcc_fg.data`), running target detection
(:mod:`dcc_fg.detection`) where the recording holds images.
"""
