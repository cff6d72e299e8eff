"""Characteristic point maps (seed 000, Wu, Dorsey & Rushmeier, EGSR 2009).

Modules, in the order a bake uses them:
- `directions`: the texel-frame direction sets (product grid, held-out grid);
- `matrix`: the apparent-reflectance matrix R (Eq. 9), Eq. 7's filtered reflectance, SNR;
- `column_sampling`: DMM06 column sampling and the weights (NNLS or the seed's clamp);
- `fit`: one texel's points: rank k, trials, the bisection on c (Table 2);
- `level`: R of a set of texels from visibility rays and BRDFs, one fit per texel, held-out SNR,
  coarse levels selecting from their children;
- `avis/`: the visible projected area a_vis (§3.4) on cube maps, its closed form, the level
  hierarchy and the Haar-compressed table the renderer reads (`haar`);
- `assemble`: one level as the payload's arrays and its report entry.
"""
