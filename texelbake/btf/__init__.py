"""BTF level of detail (seed 001): Laplacian pyramids of the BTF images, PCA per level and
channel, a Phong top-level mean, packed into two float EXR maps and evaluated with Eq. 7."""

from texelbake.btf.bake import author_btf_shader, bake_btf, btf_from_texels
from texelbake.btf.color import rgb_to_ycbcr, ycbcr_to_rgb
from texelbake.btf.compress import BTFMaps, BTFSettings, BuildInfo, build_btf_maps
from texelbake.btf.laplacian import build_pyramid, collapse
from texelbake.btf.lod import lod_from_distance, lod_weights, reconstruct_btf, reconstruct_channel
from texelbake.btf.lut import DirectionLUT, bonn_directions, build_lut, lookup_pairs
from texelbake.btf.maps_io import SHADER_BTF, read_btf_maps, write_btf_maps
from texelbake.btf.measured import MeasuredBTF, load_measured_btf, parse_ubo2003_name
from texelbake.btf.pca import pca_batched
from texelbake.btf.phong import fit_phong, phong_eval
from texelbake.btf.render import btf_lookup, btf_lookup_texels
from texelbake.btf.report import btf_errors, btf_report, compression_stats, error_vs_components

__all__ = [
    "SHADER_BTF",
    "BTFMaps",
    "BTFSettings",
    "BuildInfo",
    "DirectionLUT",
    "MeasuredBTF",
    "author_btf_shader",
    "bake_btf",
    "bonn_directions",
    "btf_from_texels",
    "btf_errors",
    "btf_lookup",
    "btf_lookup_texels",
    "btf_report",
    "build_btf_maps",
    "build_lut",
    "build_pyramid",
    "collapse",
    "compression_stats",
    "error_vs_components",
    "fit_phong",
    "load_measured_btf",
    "lod_from_distance",
    "lod_weights",
    "lookup_pairs",
    "parse_ubo2003_name",
    "pca_batched",
    "phong_eval",
    "read_btf_maps",
    "reconstruct_btf",
    "reconstruct_channel",
    "rgb_to_ycbcr",
    "write_btf_maps",
    "ycbcr_to_rgb",
]
