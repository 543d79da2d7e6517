"""The command-line programs (thin: they parse arguments and call the library).

  console.py   console-script entry points (`lrf-frames`, `lrf-register`)
  frames.py    lrf-frames: frames (and descriptors) for one's own file
  register.py  lrf-register: two scans
  multiway.py  lrf-register with more than two scans
  help.py      the shared argparse formatter
  plot.py      the figures the programs draw (`--png`)
"""
