"""nlpsf: how well must the nonlinearity of a Roman detector be calibrated for PSF modelling?

The library behind the tool: the Roman WFI PSF through a nonlinear detector measured with adaptive
moments (``experiment``), slope tables and fits (``tables``), and the two-of-three requirement
calculator (``solver``). See ``README.md`` and Plazas et al. (2016).
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("nlpsf")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.0.0+source"

__all__ = ["__version__"]
