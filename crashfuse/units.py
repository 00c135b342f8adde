"""Unit conversions, done once at the I/O boundary. Everything inside is SI."""

from __future__ import annotations

G0 = 9.80665  # standard gravity, m/s^2 per g
MPH = 0.44704  # m/s per mph
KMH = 1.0 / 3.6  # m/s per km/h
LB = 0.45359237  # kg per lb (avoirdupois pound, as mass)
MS = 1e-3  # s per ms
MM = 1e-3  # m per mm

# Accepted column suffixes: quantity -> {suffix: factor to SI}
SPEED = {"mps": 1.0, "kmh": KMH, "mph": MPH}
MASS = {"kg": 1.0, "lb": LB}
ACCEL = {"mps2": 1.0, "g": G0}
