"""Simulation with exact ground truth: procedural scenes (:mod:`.scenes`), the spike camera's
integrate-and-fire sensor with its noises (:mod:`.simulator`) and fitting those noises to a
real capture (:mod:`.sensor_fit`). numpy only."""
