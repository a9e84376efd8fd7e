"""sr_imitation: Sleeping Robots, continual robot skill learning with frozen skill memories and Nash sleep."""

__version__ = "0.2.0"
