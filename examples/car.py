"""Minimal car: a sine-wave 'pilot' steering a printed 'servo'. Replaced by the simulated car."""

import math

from asyncdonkey import Vehicle

DRIVE_LOOP_HZ = 20


class Wave:
    def __init__(self):
        self.t = 0

    def run(self):
        self.t += 1
        return math.sin(self.t / 20), 0.3


def build():
    v = Vehicle()
    v.add(Wave(), outputs=["angle", "throttle"])
    return v
