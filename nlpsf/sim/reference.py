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

import itertools
import math
import time
from dataclasses import dataclass

import numpy as np

from nlpsf.roman import photometry, seds


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


# --- the Roman default's scene, by GalSim's route -------------------------------------------------
#
# The peer of ``nlpsf solve`` with the Roman default (nlpsf/request/presets.py): optics at the position
# with the official pupil scale, the star (a blackbody, or a vendored spectrum read as a table) through
# the SCA's official bandpass, jitter and charge diffusion as Gaussians, IPC after the NL, a background
# (removed as a local sky estimate does, its own NL included), an MA table read up the ramp with
# romancal's saturation flags and an OLS or optimal (likelihood) fit, and the slope taken at the
# corrected state. Nothing below imports nlpsf's physics: GalSim draws and measures, the ramp is read
# read by read here (written from the physics as tests/library/test_ramps_readout.py's brute force
# is, vectorised over pixels), and the data files (pupil clear areas, effective areas) are read
# directly. The numbers a request fixes (MA table, read noise, background, beta0) are arguments.

#: Roman's collecting-area reference for the official bandpass: throughput = A_eff / 1 m^2.
_AREA_REFERENCE_M2 = 1.0


def official_bandpass(band: str, sca: int):
    """The SCA's official effective-area curve (roman-technical-information v8) as a GalSim Bandpass
    with throughput A_eff / 1 m^2 and the AB zeropoint, read from the vendored file."""
    import gzip

    import galsim

    from nlpsf.roman import OFFICIAL_FILTER_NAMES, official_data_dir

    path = official_data_dir() / f"Roman_effarea_v8_SCA{sca:02d}_20240301.ecsv.gz"
    with gzip.open(path, "rt") as handle:
        lines = [line for line in handle if line.strip() and not line.startswith("#")]
    names = [name.strip() for name in lines[0].split(",")]
    data = np.loadtxt(lines[1:], delimiter=",")
    wave_nm = 1000.0 * data[:, names.index("Wave")]
    area = data[:, names.index(OFFICIAL_FILTER_NAMES[band])]
    keep = np.flatnonzero(area > 0)
    lo, hi = max(keep[0] - 1, 0), min(keep[-1] + 1, area.size - 1)
    table = galsim.LookupTable(wave_nm[lo : hi + 1], area[lo : hi + 1] / _AREA_REFERENCE_M2, interpolant="linear")
    return galsim.Bandpass(table, wave_type="nm").withZeropoint("AB")


def official_clear_area_m2(band: str, sca: int) -> float:
    """The official clear area of the pupil mask ``band`` uses on ``sca`` (``exit_pupil_clear``, m^2),
    read with astropy's ECSV reader from the vendored roman-technical-information file."""
    import galsim.roman
    from astropy.table import Table

    from nlpsf.roman import OFFICIAL_PUPIL_FILES, official_pupil_dir

    kind = "long" if band in galsim.roman.longwave_bands else "short"
    table = Table.read(official_pupil_dir() / OFFICIAL_PUPIL_FILES[kind], format="ascii.ecsv")
    row = [r for r in table if str(r["sca"]).strip() == str(sca)]
    return float(row[0]["exit_pupil_clear"])


@dataclass(frozen=True)
class PeerRamp:
    """An MA table as the peer reads it: read indices per resultant (1-based frames), the frame time,
    the read noise per read, the fit ("ols" or "optimal") and the saturation level of the read signal."""

    resultants: tuple[tuple[int, ...], ...]
    frame_time_s: float
    read_noise_e: float
    fit: str = "optimal"
    saturation_e: float = 1.1e5

    @property
    def exptime_s(self) -> float:
        return self.resultants[-1][-1] * self.frame_time_s

    def tbar(self) -> np.ndarray:
        """Mean read time of each resultant in units of the exposure."""
        return np.array([np.mean(r) * self.frame_time_s for r in self.resultants]) / self.exptime_s


def romancal_usable(resultants: np.ndarray, ramp: PeerRamp) -> np.ndarray:
    """Usable resultants per pixel (the first flagged one's index) by romancal's saturation step as
    documented (stcal 1.20 flag_saturated_pixels: threshold, dilution pass, second-resultant pass),
    vectorised over pixels; a pixel left with one resultant has no slope (0: unusable).
    ``resultants``: (K, pixels) read signals."""
    R = np.asarray(resultants, dtype=np.float64)
    K, threshold = R.shape[0], ramp.saturation_e
    saturated = np.maximum.accumulate(threshold <= R, axis=0)
    flagged = saturated.copy()
    for j in range(K - 2, -1, -1):
        reads = ramp.resultants[j]
        dilution = np.mean(reads) / reads[-1]
        if dilution != 1:
            flagged[j] |= saturated[j + 1] & (R[j] >= threshold * dilution)
    if K > 2:
        r1, r2 = R[0], R[1]
        jump = (
            (r1 / np.mean(ramp.resultants[0]) * ramp.resultants[2][-1] < threshold)
            & (r2 - r1 > (threshold - r1) / len(ramp.resultants[1]))
            & saturated[2]
            & ~saturated[1]
        )
        flagged[1] |= jump
    usable = np.where(flagged.any(axis=0), np.argmax(flagged, axis=0), K)
    return np.where(usable == 1, 0, usable)


def _resultant_covariance_parts(ramp: PeerRamp) -> tuple[np.ndarray, np.ndarray]:
    """(A, D): cov(R_i, R_j) = total charge x A_ij + read_noise^2 x D_ij, built read by read (Poisson
    counts are cumulative, cov(Q_a, Q_b) = rate min(t_a, t_b); read noise independent per read)."""
    K = len(ramp.resultants)
    A, D = np.zeros((K, K)), np.zeros((K, K))
    for i, ri in enumerate(ramp.resultants):
        for j, rj in enumerate(ramp.resultants):
            a = np.array(ri, dtype=float)[:, None]
            b = np.array(rj, dtype=float)[None, :]
            A[i, j] = np.mean(np.minimum(a, b)) * ramp.frame_time_s / ramp.exptime_s
            D[i, j] = np.mean(a == b)
    return A, D


def fit_ramp(resultants: np.ndarray, usable: np.ndarray, measured: np.ndarray, ramp: PeerRamp) -> np.ndarray:
    """Fitted image (slope x exposure, e-) per pixel from its usable resultants: OLS or the generalised
    least-squares (likelihood) fit with the covariance at the measured linear charge; a pixel with no
    slope reports its first resultant over its mean time. ``resultants``: (K, pixels)."""
    R = np.asarray(resultants, dtype=np.float64)
    t = ramp.tbar()
    out = R[0] / t[0]
    A, D = _resultant_covariance_parts(ramp)
    for k in np.unique(usable):
        if k < 2:
            continue
        pix = np.flatnonzero(usable == k)
        X = np.stack([np.ones(k), t[:k]], axis=1)
        y = R[:k, pix].T  # (P, k)
        if ramp.fit == "ols":
            out[pix] = np.linalg.lstsq(X, y.T, rcond=None)[0][1]
            continue
        C = measured[pix, None, None] * A[None, :k, :k] + ramp.read_noise_e**2 * D[None, :k, :k]
        Ci = np.linalg.inv(C)
        XtCi = np.einsum("ka,pkl->pal", X, Ci)  # (P, 2, k)
        normal = XtCi @ X  # (P, 2, 2)
        rhs = np.einsum("pal,pl->pa", XtCi, y)
        out[pix] = np.linalg.solve(normal, rhs[..., None])[:, 1, 0]
    return out


@dataclass
class RampSlopes:
    """Per-centroid slopes d metric / d beta of the peer at the corrected state, and what was read."""

    dR_over_R: np.ndarray
    de1: np.ndarray
    de2: np.ndarray
    fitted_on_fewer: np.ndarray  # pixels per centroid fitted on fewer than all resultants
    unusable: np.ndarray  # pixels per centroid without a slope
    beta_points: tuple[float, float]
    elapsed_s: float

    def mean(self, metric: str) -> tuple[float, float]:
        values = getattr(self, metric)
        return float(np.mean(values)), float(np.std(values, ddof=1) / math.sqrt(values.size))


class GalSimRomanDefault:
    """GalSim's peer of the Roman default scene for one (band, SCA, position): the PSF integrated over
    the band (midpoint rule in ``n_waves`` equal bins, each bin's weight the star's photons through
    the bandpass there, GalSim's ``SED.calculateFlux``), the official pupil scale, jitter and diffusion,
    the ramp read by read with IPC after the NL (GalSim's ``applyIPC``), HSM moments.

    The monochromatic OpticalPSFs are built one at a time (GalSim's ``ChromaticOpticalPSF.interpolate``
    at a padded pupil held ~1.5 GB per wavelength); ``pupil_oversampling`` pads GalSim's pupil plane
    (see the module's note)."""

    def __init__(
        self,
        band: str,
        sca: int,
        sca_pos: tuple[float, float],
        temperature_k: float = 5270.0,
        jitter_arcsec: float = 0.006,
        diffusion_px: float = 0.332,
        n_waves: int = 16,
        pupil_oversampling: float = 2.0,
        oversampling: int = 3,
        stamp: int = 96,
        weight_cut_rho2: float = 25.0,
        ipc: bool = True,
        sed: str | None = None,
    ):
        """``sed``: a scene's SED text, ``blackbody:T`` or a vendored name (``nlpsf.roman.seds``, read as
        tabulated data only); None: the blackbody at ``temperature_k``."""
        import galsim
        import galsim.roman

        self.galsim = galsim
        self.band, self.sca, self.sca_pos = band, sca, sca_pos
        self.oversampling, self.stamp = oversampling, stamp
        self.scale = galsim.roman.pixel_scale / oversampling
        self.bandpass = official_bandpass(band, sca)
        h, c, k = 6.62607015e-34, 2.99792458e8, 1.380649e-23

        def planck(wave_nm):
            lam = np.asarray(wave_nm) * 1e-9
            return 1.0 / lam**5 / np.expm1(h * c / (lam * k * temperature_k))

        if sed is not None and seds.is_named(sed):
            wave, flambda = seds.table(sed.strip().lower())
            self.sed = galsim.SED(galsim.LookupTable(wave, flambda), "nm", "flambda")
        else:
            if sed is not None:
                temperature_k = float(sed.split(":")[1])
            self.sed = galsim.SED(galsim.LookupTable(*_planck_table(planck, self.bandpass)), "nm", "flambda")
        self.blurs = [s for s in (jitter_arcsec, diffusion_px * galsim.roman.pixel_scale) if s > 0]
        self.n_waves, self.pupil_oversampling = n_waves, pupil_oversampling
        self.ipc_kernel = galsim.roman.ipc_kernel.copy() if ipc else None
        self.hsm = galsim.hsm.HSMParams(convergence_threshold=weight_cut_threshold(weight_cut_rho2), max_mom2_iter=10000)
        self.pupil_scale_m = None  # set by _aperture

    def electrons(self, magnitude: float, exptime_s: float) -> float:
        """Electrons of an AB magnitude through the official bandpass (SED-independent for AB in-band)."""
        return 10 ** (-0.4 * (magnitude - self.bandpass.zeropoint)) * _AREA_REFERENCE_M2 * 1e4 * exptime_s

    def _aperture(self):
        import os

        galsim = self.galsim
        from galsim.roman import roman_psfs

        longwave = self.band in galsim.roman.longwave_bands
        mask = roman_psfs.pupil_plane_file_longwave if longwave else roman_psfs.pupil_plane_file_shortwave
        path = os.path.join(galsim.meta_data.share_dir, "roman", f"{mask}{self.sca}{roman_psfs.pupil_plane_filesuff}")
        image = galsim.fits.read(path).bin(4, 4).flip_ud()
        # The official rule: the binned mask as GalSim uses it (a pixel open if any sub-pixel is)
        # has the official clear area of this mask and SCA.
        n_open = int(np.count_nonzero(image.array > 0))
        self.pupil_scale_m = math.sqrt(official_clear_area_m2(self.band, self.sca) / n_open)
        return galsim.Aperture(
            lam=self.bandpass.blue_limit,
            diam=galsim.roman.diameter,
            pupil_plane_im=image,
            pupil_plane_scale=self.pupil_scale_m,
            oversampling=self.pupil_oversampling,
        )

    def wavelength_bins(self) -> tuple[np.ndarray, np.ndarray]:
        """(centre wavelengths [nm], weights summing to 1): the star's photons in each equal bin."""
        edges = np.linspace(self.bandpass.blue_limit, self.bandpass.red_limit, self.n_waves + 1)
        flux = np.array([self.sed.calculateFlux(self.bandpass.truncate(a, b)) for a, b in itertools.pairwise(edges)])
        return 0.5 * (edges[:-1] + edges[1:]), flux / flux.sum()

    def unit_stamps(self, offsets: np.ndarray) -> np.ndarray:
        """(R, stamp, stamp) unit-flux images (x N^2: each fine pixel the charge of a native pixel at
        that sub-pixel phase) at each centroid offset [fine pixels], band-integrated."""
        galsim = self.galsim
        from galsim.roman import roman_psfs

        aperture = self._aperture()
        table, x, y = roman_psfs._read_aberrations(self.sca)
        aberrations = roman_psfs._interp_aberrations_bilinear(table, x, y, galsim.PositionD(*self.sca_pos))
        aberrations[:4] = 0.0
        waves, weights = self.wavelength_bins()
        stamps = np.zeros((len(offsets), self.stamp, self.stamp))
        for wave, weight in zip(waves, weights, strict=True):
            psf = galsim.OpticalPSF(
                lam=wave, diam=galsim.roman.diameter, aberrations=aberrations * roman_psfs.zemax_wavelength / wave, aper=aperture
            )
            parts = [psf, galsim.Pixel(galsim.roman.pixel_scale)] + [galsim.Gaussian(sigma=s) for s in self.blurs]
            effective = galsim.Convolve(parts)
            for r, (dx, dy) in enumerate(np.asarray(offsets, dtype=np.float64)):
                image = effective.drawImage(
                    nx=self.stamp, ny=self.stamp, scale=self.scale, method="no_pixel", offset=(dx, dy), dtype=np.float64
                )
                stamps[r] += weight * image.array
            del psf, effective
        return stamps * self.oversampling**2

    def _ipc(self, array: np.ndarray) -> np.ndarray:
        """GalSim's applyIPC on each native-pixel image the oversampled stamp interleaves."""
        if self.ipc_kernel is None:
            return array
        out = array.copy()
        n = self.oversampling
        for a in range(n):
            for b in range(n):
                native = self.galsim.Image(np.ascontiguousarray(array[a::n, b::n]))
                native.applyIPC(self.ipc_kernel, edge_treatment="extend")
                out[a::n, b::n] = native.array
        return out

    def _resultants(self, charge: np.ndarray, ramp: PeerRamp, beta: float) -> np.ndarray:
        """(K, pixels) resultants: every read's signal Q tau - beta (Q tau)^2, coupled by IPC (after
        the NL), averaged over the resultant's reads."""
        out = []
        for reads in ramp.resultants:
            acc = np.zeros_like(charge)
            for index in reads:
                q = charge * (index * ramp.frame_time_s / ramp.exptime_s)
                acc += self._ipc(q - beta * q * q)
            out.append((acc / len(reads)).ravel())
        return np.array(out)

    def _measure(self, array: np.ndarray) -> tuple[float, float, float]:
        image = self.galsim.Image(array, scale=self.scale)
        result = self.galsim.hsm.FindAdaptiveMom(image, precision=1e-10, hsmparams=self.hsm, strict=False)
        if result.moments_status != 0:
            return math.nan, math.nan, math.nan
        return result.moments_sigma, result.observed_shape.e1, result.observed_shape.e2

    def _star_free_levels(self, background_e: float, ramp: PeerRamp, beta0: float, betas) -> list[float]:
        """A star-free pixel's fitted level at each beta (read by read, romancal's flags at beta0): what
        a local sky estimate made on the same exposure subtracts."""
        n = self.oversampling
        sky = np.full((3 * n, 3 * n), float(background_e))  # uniform: IPC's edges change nothing
        measured = self._ipc(sky).ravel()
        usable = romancal_usable(self._resultants(sky, ramp, beta0), ramp)
        centre = (3 * n // 2) * (3 * n) + 3 * n // 2
        return [float(fit_ramp(self._resultants(sky, ramp, beta), usable, measured, ramp)[centre]) for beta in betas]

    def corrected_slopes(
        self,
        stamps: np.ndarray,
        magnitude: float,
        ramp: PeerRamp,
        beta0: float,
        background_e: float,
        residual: float = 1e-2,
        half_step: float = 0.05,
    ) -> RampSlopes:
        """d metric / d beta at the corrected state, per centroid: the symmetric difference of the
        metrics at beta_c -+ h (beta_c = ``residual`` x beta0, h = ``half_step`` x beta0), each a ramp
        read read by read, with the saturation flags of the raw detector (beta0's signal) as
        romancal's saturation step sets them before the linearity correction. The metric is exact to
        second order in h at fixed flags (the fit is linear in the data); the step is wide because
        HSM returns float32 moments. After the fit the sky is removed as a local sky estimate removes
        it: a star-free pixel's fitted level at the same beta, its own NL included."""
        start = time.perf_counter()
        flux = self.electrons(magnitude, ramp.exptime_s)
        beta_c, h = residual * beta0, half_step * beta0
        betas = (beta_c - h, beta_c + h)
        rows, fewer, unusable = [], [], []
        K = len(ramp.resultants)
        sky = self._star_free_levels(background_e, ramp, beta0, betas)
        for stamp in stamps:
            charge = flux * stamp + background_e
            measured = self._ipc(charge).ravel()
            usable = romancal_usable(self._resultants(charge, ramp, beta0), ramp)
            fewer.append(int(np.sum((usable < K) & (usable >= 2))))
            unusable.append(int(np.sum(usable < 2)))
            reference = self._measure(measured.reshape(stamp.shape) - background_e)
            values = []
            for beta, level in zip(betas, sky, strict=True):
                image = fit_ramp(self._resultants(charge, ramp, beta), usable, measured, ramp)
                values.append(self._measure(image.reshape(stamp.shape) - level))
            (s_lo, e1_lo, e2_lo), (s_hi, e1_hi, e2_hi) = values
            rows.append(((s_hi - s_lo) / reference[0], e1_hi - e1_lo, e2_hi - e2_lo))
        slopes = np.asarray(rows) / (2 * h)
        return RampSlopes(*slopes.T, np.array(fewer), np.array(unusable), betas, elapsed_s=time.perf_counter() - start)


def _planck_table(planck, bandpass, n: int = 2000) -> tuple[np.ndarray, np.ndarray]:
    """The Planck f_lambda tabulated finely over the band (a LookupTable keeps the SED picklable)."""
    wave = np.linspace(bandpass.blue_limit - 1.0, bandpass.red_limit + 1.0, n)
    values = planck(wave)
    return wave, values / values.max()
