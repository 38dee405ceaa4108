"""Blender operators for the coating stage (filled in by its issue)."""

classes = ()
