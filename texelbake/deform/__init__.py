"""Appearance under deformation (seed 002 §4): warps Ψ with their Jacobians (`warps`), the
local impostor parameterization of Table 1 (`impostor`) and the look-up rotation L of
Eqs. 7–10 (`lookup`)."""

from texelbake.deform.impostor import ImpostorParams, decode_frames, impostor_params
from texelbake.deform.lookup import lookup_rotation, orthogonalize
from texelbake.deform.warps import Warp, central_jacobian, parse_warp

__all__ = ["ImpostorParams", "Warp", "central_jacobian", "decode_frames", "impostor_params",
           "lookup_rotation", "orthogonalize", "parse_warp"]
