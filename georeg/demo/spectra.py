"""Material reflectance library: analytic SWIR (0.9-2.5 um) spectra and visible RGB albedos.

Every material has a mean spectrum ``M(lambda)`` and one variability mode ``V(lambda)``; a pixel's
reflectance is ``M * (1 + c1) + c2 * V`` (c1: brightness, c2: a physical parameter such as
dryness, moisture or ageing). Shapes follow typical library curves (see docs/DEMO_SCENE.md):
USGS splib07 / ECOSTRESS (ASTER) urban and soil spectra, Herold et al. (2004) urban materials,
PROSPECT-like leaf water absorption driven by the liquid water absorption coefficient.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# material ids (index into the library arrays)
ASPHALT, CONCRETE, SOIL, GRASS, LEAF, ROOF_TAR, ROOF_METAL, ROOF_TILE = range(8)
ROOF_SHINGLE, ROOF_COOL, WATER, POOL, CAR = range(8, 13)
MATERIAL_NAMES = (
    "asphalt",
    "concrete",
    "soil",
    "grass",
    "leaf",
    "roof_tar",
    "roof_metal",
    "roof_tile",
    "roof_shingle",
    "roof_cool",
    "water",
    "pool",
    "car_paint",
)
N_MATERIALS = len(MATERIAL_NAMES)

# liquid water absorption coefficient (cm^-1), approximate values after Hale & Querry (1973) and
# Kou et al. (1993), read off their curves: peaks at 0.97, 1.2, 1.45, 1.94 um; log-interpolated.
_WATER_ALPHA = np.array(
    [
        (850, 0.043), (900, 0.068), (950, 0.39), (970, 0.45), (1000, 0.36), (1050, 0.16),
        (1100, 0.19), (1150, 0.6), (1200, 1.0), (1250, 0.9), (1300, 1.2), (1350, 3.5),
        (1400, 13.0), (1450, 29.0), (1500, 20.0), (1550, 10.0), (1600, 6.6), (1650, 5.6),
        (1700, 5.6), (1750, 8.0), (1800, 8.5), (1850, 15.0), (1900, 75.0), (1940, 115.0),
        (2000, 68.0), (2050, 40.0), (2100, 26.0), (2150, 20.0), (2200, 17.0), (2250, 18.0),
        (2300, 22.0), (2350, 31.0), (2400, 45.0), (2450, 60.0), (2500, 75.0), (2600, 120.0),
    ]
)  # fmt: skip


def water_alpha(wl: np.ndarray) -> np.ndarray:
    """Liquid water absorption coefficient (cm^-1) at wavelengths ``wl`` (nm)."""
    return np.exp(np.interp(wl, _WATER_ALPHA[:, 0], np.log(_WATER_ALPHA[:, 1])))


def _band(wl: np.ndarray, centre: float, width: float, depth: float) -> np.ndarray:
    """Multiplicative Gaussian absorption feature: 1 - depth at ``centre`` (nm), sigma ``width``."""
    return 1.0 - depth * np.exp(-0.5 * ((wl - centre) / width) ** 2)


def _hydrocarbon(wl: np.ndarray, depth: float) -> np.ndarray:
    """C-H absorptions of bitumen and polymers at 1.73 and 2.31 um (Herold et al. 2004)."""
    return (
        _band(wl, 1730, 25, depth)
        * _band(wl, 2310, 35, 1.3 * depth)
        * _band(wl, 1210, 15, 0.3 * depth)
    )


def _hydration(wl: np.ndarray, depth: float) -> np.ndarray:
    """Bound-water / OH features of minerals and cement at 1.4 and 1.9 um."""
    return _band(wl, 1410, 30, depth) * _band(wl, 1910, 45, 1.4 * depth)


def _canopy(wl: np.ndarray, plateau: float, ewt_cm: float, dry: float) -> np.ndarray:
    """PROSPECT-like canopy: NIR plateau attenuated by leaf water (Beer-Lambert) and dry matter."""
    t = (wl - 900.0) / 1600.0
    base = plateau * (1.0 - 0.12 * t)
    dm = (
        _band(wl, 1730, 40, 0.05 * dry)
        * _band(wl, 2100, 60, 0.12 * dry)
        * _band(wl, 2300, 50, 0.08 * dry)
    )
    return 0.015 + base * np.exp(-water_alpha(wl) * ewt_cm) * dm


def _dry_grass(wl: np.ndarray) -> np.ndarray:
    """Senescent grass: rising continuum with cellulose/lignin bands at 1.73, 2.1, 2.3 um."""
    t = (wl - 900.0) / 1600.0
    base = 0.30 + 0.22 * np.sqrt(np.clip(t, 0, None)) - 0.08 * t**2
    return (
        base
        * np.exp(-water_alpha(wl) * 0.004)
        * _band(wl, 2100, 55, 0.22)
        * _band(wl, 2300, 45, 0.12)
        * _band(wl, 1730, 35, 0.06)
    )


def _soil(wl: np.ndarray) -> np.ndarray:
    """Dry soil: rising into the SWIR, weak hydration bands, clay Al-OH doublet near 2.2 um."""
    t = (wl - 900.0) / 1600.0
    base = 0.22 + 0.20 * (1.0 - np.exp(-t / 0.35)) - 0.04 * np.clip(t - 0.8, 0, None) / 0.2
    return base * _hydration(wl, 0.06) * _band(wl, 2205, 18, 0.08) * _band(wl, 2165, 12, 0.03)


def swir_library(wl: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean spectra ``M`` and variability modes ``V``, both (N_MATERIALS, len(wl)) reflectance."""
    wl = np.asarray(wl, dtype=np.float64)
    t = (wl - 900.0) / 1600.0
    flat = np.ones_like(wl)
    M = np.zeros((N_MATERIALS, wl.size))
    V = np.zeros_like(M)
    asph_new = (0.055 + 0.045 * t) * _hydrocarbon(wl, 0.10)
    asph_old = (0.13 + 0.09 * t) * _hydrocarbon(wl, 0.04) * _hydration(wl, 0.03)
    M[ASPHALT], V[ASPHALT] = asph_new, asph_old - asph_new  # c2: ageing 0..1
    conc = (0.30 + 0.08 * (1.0 - ((wl - 1700.0) / 800.0) ** 2)) * _hydration(wl, 0.07)
    conc = conc * _band(wl, 2340, 25, 0.06)  # carbonate
    M[CONCRETE], V[CONCRETE] = conc, -0.10 * (0.5 + t)  # c2: soiling
    soil = _soil(wl)
    wet = 0.65 * soil * np.exp(-water_alpha(wl) * 0.015)
    M[SOIL], V[SOIL] = soil, wet - soil  # c2: moisture 0..1
    green = _canopy(wl, 0.38, 0.025, 0.5) * 0.85 + 0.15 * soil
    M[GRASS], V[GRASS] = green, _dry_grass(wl) - green  # c2: dryness 0..1
    leaf = _canopy(wl, 0.50, 0.035, 0.6)
    M[LEAF], V[LEAF] = leaf, (_canopy(wl, 0.50, 0.045, 0.6) - leaf)  # c2: extra water
    tar = (0.065 + 0.03 * t) * _hydrocarbon(wl, 0.12)
    M[ROOF_TAR], V[ROOF_TAR] = tar, 0.10 * flat * _hydration(wl, 0.05)  # c2: gravel cover
    M[ROOF_METAL], V[ROOF_METAL] = 0.46 - 0.10 * t, -0.18 * flat  # c2: paint/weathering
    tile = (0.36 + 0.20 * (1.0 - np.exp(-t / 0.15)) - 0.06 * t) * _hydration(wl, 0.05)
    M[ROOF_TILE], V[ROOF_TILE] = tile * _band(wl, 2200, 25, 0.04), -0.10 * flat
    shingle = (0.10 + 0.04 * t) * _hydrocarbon(wl, 0.08)
    M[ROOF_SHINGLE], V[ROOF_SHINGLE] = shingle, 0.08 * flat
    cool = (0.74 - 0.30 * t) * _hydrocarbon(wl, 0.14) * _hydration(wl, 0.04)
    M[ROOF_COOL], V[ROOF_COOL] = cool, -0.25 * (1.0 - 0.5 * t)  # c2: soiling
    water = 0.004 + 0.025 * np.exp(-(wl - 900.0) / 70.0)
    M[WATER], V[WATER] = water, 0.012 * np.exp(-(wl - 900.0) / 150.0)  # c2: turbidity
    M[POOL], V[POOL] = water * 1.2, 0.5 * V[WATER]
    car = (0.22 - 0.05 * t) * _hydrocarbon(wl, 0.10)
    M[CAR], V[CAR] = car, 0.20 * flat * _hydrocarbon(wl, 0.1)  # c2: white vs dark paint
    return M, V


# linear visible albedo (R, G, B) of each material and its variability mode
RGB_MEAN = np.array(
    [
        (0.075, 0.075, 0.080), (0.36, 0.35, 0.33), (0.30, 0.23, 0.16), (0.055, 0.105, 0.035),
        (0.035, 0.062, 0.028), (0.085, 0.085, 0.085), (0.40, 0.42, 0.44), (0.40, 0.18, 0.10),
        (0.11, 0.10, 0.09), (0.70, 0.71, 0.72), (0.030, 0.050, 0.055), (0.12, 0.36, 0.46),
        (0.14, 0.14, 0.15),
    ]
)  # fmt: skip
RGB_VAR = np.array(
    [
        (0.10, 0.10, 0.09), (-0.10, -0.10, -0.10), (-0.13, -0.10, -0.07), (0.17, 0.10, 0.07),
        (0.00, 0.01, 0.00), (0.10, 0.10, 0.09), (-0.15, -0.12, -0.10), (-0.08, -0.04, -0.02),
        (0.08, 0.06, 0.05), (-0.25, -0.25, -0.25), (0.03, 0.04, 0.02), (0.00, 0.05, 0.05),
        (0.40, 0.08, 0.05),
    ]
)  # fmt: skip

# standard deviation of the per-pixel texture added to c1, per material
TEXTURE_AMP = np.array(
    [0.18, 0.10, 0.16, 0.22, 0.30, 0.10, 0.05, 0.08, 0.10, 0.06, 0.05, 0.04, 0.02]
)


def wavelengths(bands: int) -> tuple[np.ndarray, np.ndarray]:
    """Band centres evenly spaced 900..2500 nm and their FWHM (1.2 x spacing), in nm."""
    wl = np.linspace(900.0, 2500.0, bands)
    step = 1600.0 / max(bands - 1, 1)
    return wl, np.full(bands, round(1.2 * step, 3))


def atmosphere_transmittance(wl: np.ndarray) -> np.ndarray:
    """Two-way-ish atmospheric transmittance: H2O at 0.94, 1.13, 1.38, 1.87 um and CO2 at 2.01 um."""
    tau = (
        0.05
        + 0.25 * np.exp(-0.5 * ((wl - 940) / 25) ** 2)
        + 0.35 * np.exp(-0.5 * ((wl - 1135) / 25) ** 2)
        + 3.2 * np.exp(-0.5 * ((wl - 1380) / 45) ** 2)
        + 3.6 * np.exp(-0.5 * ((wl - 1880) / 55) ** 2)
        + 0.30 * np.exp(-0.5 * ((wl - 2010) / 15) ** 2)
        + 1.0 * np.clip((wl - 2400) / 100, 0, None) ** 2
    )
    return np.exp(-tau)


def noise_sigma(wl: np.ndarray) -> np.ndarray:
    """Sensor noise (reflectance units) after atmospheric correction: low SNR in absorption bands."""
    sigma = 0.0025 * (wl / 1000.0) ** 2.0 / atmosphere_transmittance(wl)
    return np.minimum(sigma, 0.25)


def diffuse_ratio(wl: np.ndarray, elevation_deg: float) -> np.ndarray:
    """Skylight / direct-sun irradiance ratio on flat ground: falls as lambda^-2, rises at low sun."""
    return 0.10 * (1000.0 / wl) ** 2 / max(np.sin(np.radians(elevation_deg)), 0.05) ** 0.5


def reflectance_at(wl_nm: float) -> tuple[np.ndarray, np.ndarray]:
    """``M`` and ``V`` of every material at a single wavelength (for LiDAR intensities)."""
    M, V = swir_library(np.array([float(wl_nm)]))
    return M[:, 0], V[:, 0]


@dataclass(frozen=True)
class Sun:
    """Sun direction: azimuth clockwise from north, elevation above the horizon (degrees)."""

    azimuth_deg: float
    elevation_deg: float

    def vector(self) -> np.ndarray:
        """Unit vector towards the sun in (east, north, up)."""
        az, el = np.radians(self.azimuth_deg), np.radians(self.elevation_deg)
        return np.array([np.sin(az) * np.cos(el), np.cos(az) * np.cos(el), np.sin(el)])
