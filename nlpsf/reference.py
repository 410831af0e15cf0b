"""The GalSim pipeline the paper used, as the reference our numbers are checked against.

``galsim.roman.getPSF`` -> ``Convolve`` with the 0.11" pixel -> ``drawImage(method='no_pixel')``
at p/N on a float64 stamp -> multiply by N^2 -> ``applyNonlinearity`` -> ``hsm.FindAdaptiveMom``.
GalSim is an optional dependency (``pip install nlpsf[reference]``); this module is used by the
cross-check tests and the benchmark only, never by the service.

GalSim's ``getPSF`` pads the pupil plane only to twice the telescope diameter, so its PSF image is
sampled at about Nyquist and then interpolated with a quintic kernel; for many SCA/band pairs that
changes the drawn PSF by 1-2.5 % of its peak (and sigma by up to 2.5 %). ``pupil_oversampling`` > 1
builds exactly the same PSF (same files, binning, scale, aberrations, wavelength) with the pupil
plane padded further (GalSim's ``Aperture(oversampling=...)``), which converges: at 4 it matches
nlpsf's Fourier-exact optics to ~1e-5 of the peak.

Two facts about the peer matter for comparisons: ``FindAdaptiveMom`` stops iterating at its
``precision`` argument (HSMParams' ``convergence_threshold`` only sets the weight cut), and it
returns sigma and e1, e2 rounded to float32.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from . import photometry


def weight_cut_threshold(weight_cut_rho2: float) -> float:
    """HSMParams.convergence_threshold that makes GalSim >= 2.4 cut its weight at this rho^2."""
    return 10.0 * math.exp(-0.5 * weight_cut_rho2)


@dataclass
class GalSimMeasurement:
    """Per-realization measurements from the GalSim pipeline (arrays over realizations)."""

    sigma0: np.ndarray
    e1_0: np.ndarray
    e2_0: np.ndarray
    sigma: np.ndarray
    e1: np.ndarray
    e2: np.ndarray
    reference_images: list[np.ndarray] | None
    elapsed_s: float

    @property
    def dR_over_R(self) -> np.ndarray:
        return self.sigma / self.sigma0 - 1.0

    @property
    def de1(self) -> np.ndarray:
        return self.e1 - self.e1_0

    @property
    def de2(self) -> np.ndarray:
        return self.e2 - self.e2_0


class GalSimPipeline:
    """The paper's pipeline for one (band, SCA), kept so the PSF is built once."""

    def __init__(
        self,
        band: str,
        sca: int,
        oversampling: int = 3,
        stamp: int = 96,
        weight_cut_rho2: float = 25.0,
        pupil_oversampling: float = 1.0,
        sca_pos: tuple[float, float] | None = None,
        blur_sigmas_arcsec: tuple[float, ...] = (),
        ipc_kernel: np.ndarray | None = None,
        ipc_order: str = "after",
        n_waves: int | None = None,
    ):
        """``sca_pos``, ``blur_sigmas_arcsec`` (Gaussians convolved with the PSF: jitter,
        diffusion), ``ipc_kernel``/``ipc_order`` (GalSim's ``applyIPC`` on the native-pixel images,
        see :meth:`apply_ipc`) and ``n_waves`` (a flat-f_nu star drawn through the bandpass with
        GalSim's ``ChromaticOpticalPSF.interpolate`` over ``n_waves`` wavelengths) are the scene
        effects' peers; the defaults are the paper's pipeline."""
        import galsim
        import galsim.roman

        self.galsim = galsim
        self.band, self.sca = band, sca
        self.oversampling, self.stamp = oversampling, stamp
        bandpass = galsim.roman.getBandpasses(AB_zeropoint=True)[band]
        self.bandpass = bandpass
        position = None if sca_pos is None else galsim.PositionD(*sca_pos)
        self.chromatic = n_waves is not None
        if self.chromatic:
            psf = _get_psf_oversampled(sca, band, None, pupil_oversampling, position, bandpass, n_waves)
        elif pupil_oversampling == 1.0:
            psf = galsim.roman.getPSF(sca, band, SCA_pos=position, wavelength=bandpass)
        else:
            psf = _get_psf_oversampled(sca, band, bandpass.effective_wavelength, pupil_oversampling, position)
        parts = [psf, galsim.Pixel(galsim.roman.pixel_scale)] + [galsim.Gaussian(sigma=s) for s in blur_sigmas_arcsec if s > 0]
        self.effective = galsim.Convolve(parts)
        self.ipc_kernel = None if ipc_kernel is None else galsim.Image(np.asarray(ipc_kernel, dtype=np.float64))
        self.ipc_order = ipc_order
        self.scale = galsim.roman.pixel_scale / oversampling
        self.hsm = galsim.hsm.HSMParams(convergence_threshold=weight_cut_threshold(weight_cut_rho2), max_mom2_iter=10000)

    def electrons(self, magnitude: float, exptime_s: float) -> float:
        return 10 ** (-0.4 * (magnitude - self.bandpass.zeropoint)) * self.galsim.roman.collecting_area * exptime_s

    def draw(self, flux: float, offset: tuple[float, float]) -> np.ndarray:
        kwargs = dict(nx=self.stamp, ny=self.stamp, scale=self.scale, method="no_pixel", offset=offset, dtype=np.float64)
        if self.chromatic:
            sed = self.galsim.SED("1", "nm", "fnu").withFlux(1.0, self.bandpass)  # flat f_nu
            star = self.galsim.Convolve(self.effective, self.galsim.DeltaFunction() * sed)
            image = star.drawImage(self.bandpass, **kwargs)  # photons for unit flux through the band
            image *= flux
        else:
            image = self.effective.withFlux(flux).drawImage(**kwargs)
        image *= self.oversampling**2
        return image

    def apply_ipc(self, image) -> None:
        """GalSim's ``applyIPC`` on each of the N^2 native-pixel images the oversampled image
        interleaves (fine pixel (i, j) = native pixel sample at sub-pixel phase (i mod N, j mod N));
        this is how GalSim would apply a native-pixel kernel, with no assumption about taps."""
        n = self.oversampling
        array = image.array
        for a in range(n):
            for b in range(n):
                native = self.galsim.Image(array[a::n, b::n].copy())
                native.applyIPC(self.ipc_kernel, edge_treatment="extend")
                array[a::n, b::n] = native.array

    def measure(self, image, precision: float = 1e-10):
        result = self.galsim.hsm.FindAdaptiveMom(image, precision=precision, hsmparams=self.hsm, strict=False)
        if result.moments_status != 0:
            return math.nan, math.nan, math.nan
        return result.moments_sigma, result.observed_shape.e1, result.observed_shape.e2

    def run(
        self,
        magnitude: float,
        beta: float,
        offsets: np.ndarray,
        exptime_s: float,
        redraw: bool = True,
        keep_images: bool = False,
        precision: float = 1e-10,
    ) -> GalSimMeasurement:
        """Measure the reference and the NL image for each centroid offset (fine pixels).

        ``redraw``: draw the image again for the NL measurement, as the paper's code does.
        """
        start = time.perf_counter()
        flux = self.electrons(magnitude, exptime_s)
        rows = []
        images = []
        for dx, dy in np.asarray(offsets, dtype=np.float64):
            image = self.draw(flux, (dx, dy))
            if keep_images:
                images.append(image.array.copy())
            reference = self.measure(image, precision)
            distorted = self.draw(flux, (dx, dy)) if redraw else image.copy()
            if self.ipc_kernel is not None:
                reference_image = image.copy()
                self.apply_ipc(reference_image)
                reference = self.measure(reference_image, precision)
                if self.ipc_order == "before":
                    self.apply_ipc(distorted)
            distorted.applyNonlinearity(lambda x, b: x - b * x * x, beta)
            if self.ipc_kernel is not None and self.ipc_order == "after":
                self.apply_ipc(distorted)
            rows.append(reference + self.measure(distorted, precision))
        values = np.asarray(rows, dtype=np.float64)
        return GalSimMeasurement(
            *values.T, reference_images=images if keep_images else None, elapsed_s=time.perf_counter() - start
        )


def _get_psf_oversampled(
    sca: int,
    band: str,
    wavelength_nm: float | None,
    pupil_oversampling: float,
    position=None,
    bandpass=None,
    n_waves: int | None = None,
):
    """``galsim.roman.getPSF(sca, band, wavelength=...)`` with a finer-sampled pupil plane.

    Every step is the one ``galsim.roman.roman_psfs`` takes (file, scale from the header, bin 4,
    flip, bilinear aberrations at the SCA centre, scaled to the wavelength); only the Aperture's
    ``oversampling`` differs.
    """
    import os

    import galsim
    import galsim.roman
    from galsim.roman import roman_psfs

    mask = roman_psfs.pupil_plane_file_longwave if band in galsim.roman.longwave_bands else roman_psfs.pupil_plane_file_shortwave
    path = os.path.join(galsim.meta_data.share_dir, "roman", f"{mask}{sca}{roman_psfs.pupil_plane_filesuff}")
    image = galsim.fits.read(path, read_header=True)
    image.scale *= image.header["HIERARCH PUPIL SCALE FACTOR"] * 1e-6
    image = image.bin(4, 4).flip_ud()
    aperture = galsim.Aperture(
        lam=wavelength_nm if wavelength_nm is not None else bandpass.blue_limit,
        diam=galsim.roman.diameter,
        obscuration=galsim.roman.obscuration,
        pupil_plane_im=image,
        oversampling=pupil_oversampling,
    )
    table, x, y = roman_psfs._read_aberrations(sca)
    centre = galsim.PositionD(galsim.roman.n_pix / 2, galsim.roman.n_pix / 2)
    aberrations = roman_psfs._interp_aberrations_bilinear(table, x, y, position or centre)
    aberrations[:4] = 0.0
    if wavelength_nm is None:
        # GalSim's chromatic Roman PSF (getPSF with wavelength=None, n_waves), same aperture.
        psf = galsim.ChromaticOpticalPSF(
            lam=roman_psfs.zemax_wavelength, diam=galsim.roman.diameter, aberrations=aberrations, aper=aperture
        )
        return psf.interpolate(waves=np.linspace(bandpass.blue_limit, bandpass.red_limit, n_waves), oversample_fac=1.5)
    scaled = aberrations * roman_psfs.zemax_wavelength / wavelength_nm
    return galsim.OpticalPSF(lam=wavelength_nm, diam=galsim.roman.diameter, aberrations=scaled, aper=aperture)


def galsim_electrons(band: str, magnitude: float, exptime_s: float) -> tuple[float, float]:
    """(GalSim's, ours) electrons for a magnitude: the photometry cross-check."""
    import galsim.roman

    bandpass = galsim.roman.getBandpasses(AB_zeropoint=True)[band]
    theirs = 10 ** (-0.4 * (magnitude - bandpass.zeropoint)) * galsim.roman.collecting_area * exptime_s
    return theirs, float(photometry.magnitude_to_electrons(magnitude, band, exptime_s, sca=18, throughput="galsim-2021"))
