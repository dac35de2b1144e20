"""Experiments that calibrate Iobj on one's own display (issue 31): detection thresholds
(`hostd experiment threshold`, QUEST+ from the questplus package) and the paper's Section IV
similarity test (`hostd experiment similarity`), answered on a loopback web page, written to
SQLite answer by answer, giving the thresholds CSV and the scores CSV that `hostd fit` reads,
and a calibration file (hostd.perception.calibration) every command uses.

This room uses perception/, codec/, render/ and the daemon's control socket; nothing outside
it imports it. The procedures are numpy grids (hostd.experiment.psychometric); questplus, its
extra's dependency, is the reference their posterior is tested against.
"""
