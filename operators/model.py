"""Blender operators for the model stage (filled in by its issue)."""

classes = ()
