"""armourcam: the application layer (command line, synthetic scenes, bag tools, graph launcher)."""

__version__ = "0.1.0"
