"""Blender operators for the instances stage (filled in by its issue)."""

classes = ()
