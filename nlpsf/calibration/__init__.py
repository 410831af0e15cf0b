"""Residual nonlinearity in the calibrator's terms (docs/calibration.md).

A linearity calibration leaves a residual r(Q), corrected signal minus true charge at charge Q. Under the
pipeline's correction on every resultant (``nlpsf.sim.ramps.correction``) it enters the image linearly, so a
PSF metric responds to it through a kernel, Delta metric = integral K(Q) r(Q) dQ:

- ``kernel``: the response samples of a star (``Response``) and the kernel on charge nodes (``Kernel``);
- ``response``: those samples from a prepared simulation or a solve request;
- ``residuals``: residual curves, polynomials, shape families and linearity reference files;
- ``requirement``: the two-of-three calculator for a residual's scale, and the envelope eps(Q).

The quadratic residual -Delta_beta Q^2 is the solver's Delta_beta: integral K(Q) (-Q^2) dQ is its slope.
"""

from .kernel import KERNEL_METRICS, Kernel, Response, nodes
from .response import star_response

__all__ = ["KERNEL_METRICS", "Kernel", "Response", "nodes", "star_response"]
