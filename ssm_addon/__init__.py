"""SSM Builder core: statistical shape models from segmented volumes, without Blender."""

__version__ = "0.1.0"

