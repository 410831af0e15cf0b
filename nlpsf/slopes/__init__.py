"""Where slopes come from: the paper's tables and their files (``tables``), the Roman default's
field grid (``fieldgrid``), the simulator's slopes for a request (``source``), building tables
(``tablebuild``), the fidelity levels (``fidelity``) and their measured trade-off (``tradeoff``).

``from nlpsf import slopes`` is the simulator's slope function (``nlpsf.sim.experiment.slopes``),
not this package: import its modules by name (``from nlpsf.slopes import tables``).
"""
