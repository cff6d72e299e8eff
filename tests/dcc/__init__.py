"""Tests that open our output in a real DCC (Blender as bpy) and of the Blender add-on."""
