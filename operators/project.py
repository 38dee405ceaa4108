"""Blender operators for the project stage (filled in by its issue)."""

classes = ()
