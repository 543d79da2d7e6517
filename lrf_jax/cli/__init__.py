"""The command-line programs (thin: they parse arguments and call the library).

  console.py   console-script entry points (`lrf-frames`, `lrf-register`, `lrf-batch`,
               `lrf-compile`)
  frames.py    lrf-frames: frames (and descriptors) for one's own file
  register.py  lrf-register: two scans
  multiway.py  lrf-register with more than two scans (or --out-dir), on an engine
  batch.py     lrf-batch: a data set's frames or registrations, resumable
  compile.py   lrf-compile: every kernel compiled ahead, in parallel
  view.py      lrf-view: models and registrations in the browser (lrf_jax.viz)
  options.py   register's flags, derived from `RegisterOptions`
  interrupt.py Ctrl-C: one line, exit 130, never lost
  help.py      the shared argparse formatter
  plot.py      the figures the programs draw (`--png`)
"""
