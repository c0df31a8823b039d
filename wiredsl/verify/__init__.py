"""`wiredsl verify`: the paper's edge verification (its Figure 7) from a researcher's own images and detector,
and the pipeline fitted to it. One stage a module:

  images.py        image files in (headers checked before decoding), grouped into frames, each with a pose
  board.py         each image's pose from the scene's calibration board (`--poses board`, solvePnP)
  detectors.py     OpenCV's Canny, LSD, Harris and Shi-Tomasi, and plug-ins (entry-point group wiredsl.detectors)
  verification.py  the scene projected for each image (hidden lines removed), model features sampled and
                   searched for along their normals; corners within the match radius; stereo corner matching
  refine.py        optional pose refinement aligning the model with the detected edges
  fit.py           each effect's parameters with bootstrap intervals, written as a pipeline block (.wd)
  report.py        the table (CSV, JSON) and the Figure 7 plot
  command.py       the command, as cli.py registers it

OpenCV (extra `images`) and matplotlib (extra `plot`) are imported only here.
"""
