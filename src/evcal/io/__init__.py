"""Readers and writers of recordings and calibration files."""
