"""The pendulum (left/right swinging) whisk-broom scanner: model and simulator."""
from swathflow.sensors.pendulum.model import PendulumModel

__all__ = ["PendulumModel"]
