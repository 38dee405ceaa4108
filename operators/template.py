"""Blender operators for the template stage (filled in by its issue)."""

classes = ()
