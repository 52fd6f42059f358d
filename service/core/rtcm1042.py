"""RTCM 3 message 1042 (BDS satellite ephemeris, RTCM 10403.3 section 3.5.13, Table
3.5-130 ff.) as a table of :class:`~service.core.types.Ephemeris` fields: the one mapping the
RTCM driver decodes with and the virtual receiver encodes with.

Each row: the Ephemeris attribute, the data field, and the factor from the field's scaled
value (as pyrtcm gives it, in the field's unit) to the attribute's unit: semicircles times
the ICD's pi (BDS-SIS-ICD-B1I-3.0 5.2.4.12), TGD in ns to s.
"""

from __future__ import annotations

from service.core.constants import ICD_PI

EPH_1042_FIELDS: tuple[tuple[str, str, float], ...] = (
    ("week", "DF489", 1.0),
    ("toe_sow_s", "DF505", 1.0),
    ("toc_sow_s", "DF493", 1.0),
    ("af0_s", "DF496", 1.0),
    ("af1_s_s", "DF495", 1.0),
    ("af2_s_s2", "DF494", 1.0),
    ("sqrt_a_sqrt_m", "DF504", 1.0),
    ("e", "DF502", 1.0),
    ("i0_rad", "DF509", ICD_PI),
    ("omega0_rad", "DF507", ICD_PI),
    ("omega_rad", "DF511", ICD_PI),
    ("m0_rad", "DF500", ICD_PI),
    ("delta_n_rad_s", "DF499", ICD_PI),
    ("omega_dot_rad_s", "DF512", ICD_PI),
    ("idot_rad_s", "DF491", ICD_PI),
    ("cuc_rad", "DF501", 1.0),
    ("cus_rad", "DF503", 1.0),
    ("crc_m", "DF510", 1.0),
    ("crs_m", "DF498", 1.0),
    ("cic_rad", "DF506", 1.0),
    ("cis_rad", "DF508", 1.0),
    ("tgd1_s", "DF513", 1e-9),
    ("tgd2_s", "DF514", 1e-9),
    ("health", "DF515", 1.0),
    ("aode", "DF492", 1.0),
    ("aodc", "DF497", 1.0),
)
EPH_1042_INT_FIELDS = frozenset({"week", "health", "aode", "aodc"})
"""Attributes carried as integers."""
