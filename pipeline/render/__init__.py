"""Rendering the target satellite with Blender (bpy)."""
