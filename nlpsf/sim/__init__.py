"""The simulator: the effective PSF (``optics``), stamps (``render``), adaptive moments
(``moments``), the nonlinearity and its limits (``detector``), the scene effects (``scene``),
up-the-ramp reads and fits (``ramps``), one simulation (``experiment``), the GalSim pipeline the
paper used (``reference``) and sweeps over a grid, locally or on dask (``sweep``, ``cluster``).

It imports the Roman data (``nlpsf.roman``) and nothing above it.
"""
