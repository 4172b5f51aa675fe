"""Measurements in and out: FRF files (``shared/FRF_FORMAT.md``), time-domain data to FRF."""

from .frf_file import FrfMeasurement, load_frf, load_frf_dir, save_frf

__all__ = ["FrfMeasurement", "load_frf", "load_frf_dir", "save_frf"]
