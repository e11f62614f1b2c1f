"""Jerlov water types for the synthetic scene: beta_D, beta_B and B_inf from published tables.

Every number below is copied from a published table; nothing is fitted or tuned here. What is derived, and how:

Wavelengths. A camera channel integrates over a band; Akkaynak & Treibitz's wideband coefficients (2018) need the
camera's spectral sensitivity, which we do not have. We read each table at one wavelength per channel, the
tabulated wavelength nearest the peak of a typical camera's sensitivity: R = 600 nm, G = 525 nm, B = 475 nm
(the tables step by 25 nm; no interpolation, so each coefficient is a table entry). For narrow channels the
wideband coefficients of Akkaynak & Treibitz (2018) reduce to these single-wavelength values.

beta_D and beta_B = K_d(lambda) of [Jerlov 1976]. The image formation model attenuates the direct signal and
builds up the backscatter with the water's attenuation coefficient beta(lambda): in Akkaynak & Treibitz's revised
model (2018, Eqs. for beta^D_c and beta^B_c) both are wideband averages of the same beta(lambda), so for a
narrow channel beta_D = beta_B = beta(lambda_c). Jerlov's types are defined by the diffuse attenuation K_d of
downwelling irradiance, and Akkaynak et al. (2017, Fig. 1) use these spectra as the attenuation coefficient
beta(lambda) of the ten types; we do the same. (K_d is smaller than the beam attenuation c = a + b, which counts
every scattered photon as lost; images keep much of the forward-scattered light, so their effective attenuation
lies between the two. With c instead, coastal waters would hide a seabed 3 m away.)

B_inf = b / (a + b) at the same wavelengths, from [Solonenko & Mobley 2015]. Akkaynak & Treibitz (2018) define
the veiling light as B_inf(lambda) = b(lambda) E(d, lambda) / c(lambda): the scattering coefficient b over the
beam attenuation c = a + b, times the ambient light E. The scene's clean radiance J is albedo times shading under
a white light of level 1 (as in white-balanced images), so E = 1 and B_inf = b / c per channel.

Which types. Jerlov tabulates all ten types (I, IA, IB, II, III, 1C, 3C, 5C, 7C, 9C); the a and b we could cite
cover I, II, III, 1C, 3C, 5C, 7C and 9C, so only those eight are offered (IA and IB have no cited b, hence no
B_inf). Solonenko & Mobley's a and b are fitted to reproduce the Jerlov K_d spectra, and K_d constrains b only
weakly (through backscattering): their oceanic II and III come out with more scattering than coastal 1C, so
their veiling light is brighter. That is the published table; we do not correct it.

Sources (the numbers were read from public transcriptions of these tables, not from the printed pages: two
independent transcriptions of Jerlov's Table XXVII agree on every K_d used here; two independent transcriptions of
Solonenko & Mobley's appendix tables agree on every a and b of 1C, 3C, 5C and 7C used here, and the a and b of I,
II, III and 9C come from one of them):
- [Jerlov 1976] N. G. Jerlov, Marine Optics, 2nd ed., Elsevier Oceanography Series 14 (1976), Table XXVII
  (p. 135): downward irradiance attenuation coefficients K_d (per metre) of the oceanic and coastal water types.
- [Solonenko & Mobley 2015] M. G. Solonenko and C. D. Mobley, "Inherent optical properties of Jerlov water
  types", Applied Optics 54(17), 5392-5401 (2015), doi:10.1364/AO.54.005392, Appendix A, Tables 6-8: absorption
  a(lambda) and scattering b(lambda) (per metre) of every Jerlov type, 300-700 nm. In the printed Table 7 the
  600-700 nm rows of type 5C repeat its 300-400 nm rows (a misprint: a(600 nm) = 5.36 / m), so 5C's red a and b
  are read at 575 nm, the nearest intact row.
- [Akkaynak et al. 2017] D. Akkaynak, T. Treibitz, T. Shlesinger, R. Tamir, Y. Loya, D. Iluz, "What is the space
  of attenuation coefficients in underwater computer vision?", CVPR 2017.
- [Akkaynak & Treibitz 2018] D. Akkaynak and T. Treibitz, "A revised underwater image formation model", CVPR 2018.
"""

from __future__ import annotations

from dataclasses import dataclass

RGB = tuple[float, float, float]

WAVELENGTHS_NM: tuple[int, int, int] = (600, 525, 475)
"""The wavelength (nm) each channel (R, G, B) reads the tables at."""

JERLOV_KD: dict[str, RGB] = {
    # [Jerlov 1976] Table XXVII, K_d per metre at 600, 525, 475 nm (R, G, B).
    "I": (0.235, 0.043, 0.018),
    "IA": (0.24, 0.048, 0.025),
    "IB": (0.245, 0.054, 0.033),
    "II": (0.26, 0.076, 0.062),
    "III": (0.295, 0.116, 0.116),
    "1C": (0.30, 0.13, 0.17),
    "3C": (0.33, 0.20, 0.29),
    "5C": (0.40, 0.31, 0.43),
    "7C": (0.48, 0.49, 0.71),
    "9C": (0.60, 0.78, 1.23),
}

SOLONENKO_MOBLEY_A: dict[str, RGB] = {
    # [Solonenko & Mobley 2015] Tables 6-8, absorption a per metre at 600, 525, 475 nm (5C: 575, 525, 475 nm).
    "I": (0.228, 0.046, 0.019),
    "II": (0.228, 0.0469, 0.0228),
    "III": (0.229, 0.0507, 0.0335),
    "1C": (0.236, 0.068, 0.077),
    "3C": (0.239, 0.078, 0.105),
    "5C": (0.119, 0.127, 0.204),
    "7C": (0.301, 0.233, 0.388),
    "9C": (0.390, 0.430, 0.709),
}

SOLONENKO_MOBLEY_B: dict[str, RGB] = {
    # [Solonenko & Mobley 2015] Tables 6-8, scattering b per metre at 600, 525, 475 nm (5C: 575, 525, 475 nm).
    "I": (0.00122, 0.00205, 0.00306),
    "II": (0.309, 0.387, 0.459),
    "III": (0.845, 1.06, 1.26),
    "1C": (0.314, 0.395, 0.469),
    "3C": (0.916, 1.15, 1.36),
    "5C": (1.23, 1.44, 1.71),
    "7C": (2.03, 2.54, 3.01),
    "9C": (2.69, 3.38, 4.01),
}

WATER_TYPES: tuple[str, ...] = ("I", "II", "III", "1C", "3C", "5C", "7C", "9C")
"""The types offered: those with both a cited K_d and a cited a, b (clearest to most turbid)."""

SOURCES = (
    "beta_D = beta_B = K_d: N. G. Jerlov, Marine Optics, 2nd ed. (1976), Table XXVII; "
    "B_inf = b / (a + b): M. G. Solonenko and C. D. Mobley, Applied Optics 54(17):5392 (2015), Tables 6-8; "
    "R, G, B read at 600, 525, 475 nm (5C's a, b at 575 nm for R)"
)


@dataclass(frozen=True)
class WaterType:
    """One Jerlov type's medium for the scene (per metre; B_inf in [0, 1])."""

    name: str
    beta_D: RGB
    beta_B: RGB
    B_inf: RGB


def water_type(name: str) -> WaterType:
    """The medium of Jerlov type `name` (one of `WATER_TYPES`), derived as the module docstring says."""
    if name not in WATER_TYPES:
        raise KeyError(f"unknown water type {name!r}; known: {', '.join(WATER_TYPES)}")
    kd = JERLOV_KD[name]
    a, b = SOLONENKO_MOBLEY_A[name], SOLONENKO_MOBLEY_B[name]
    veil = tuple(bc / (ac + bc) for ac, bc in zip(a, b, strict=True))
    return WaterType(name, kd, kd, veil)  # type: ignore[arg-type]
