"""Blender operators for the landmarks stage (filled in by its issue)."""

classes = ()
