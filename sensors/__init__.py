"""The built-in sensor plugins: the pendulum whisk-broom scanner and the push-broom camera.

They register through the entry-point group ``swathflow.sensors`` like any third-party
plugin; the interface they implement is :mod:`swathflow.sensormodel`.
"""
