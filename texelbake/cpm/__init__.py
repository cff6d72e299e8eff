"""Characteristic point maps (seed 000, Wu, Dorsey & Rushmeier, EGSR 2009).

Modules, in the order a bake uses them:
- `directions`: the texel-frame direction sets (product grid, held-out grid);
- `matrix`: the apparent-reflectance matrix R (Eq. 9), Eq. 7's filtered reflectance, SNR;
- `column_sampling`: DMM06 column sampling and the weights (NNLS or the seed's clamp);
- `texel_fit`: a texel's fit parameters (`FitParams`) and result (`TexelFit`), assembled once
  for both fitting paths;
- `search`: the draws, trials and bisection on c (Table 2), written once for both paths;
- `fit`: one texel's points on its R (the per-texel path);
- `gram/`: the same fit from Gram matrices, for many texels at once (the batched path);
- `level`: what fitting a level reads (texels, samples, directions, visibility rays, BRDFs,
  a coarse level's candidates from its children);
- `dense`: a_vis and the held-out truth from a level's dense samples;
- `level_batched`, `level_per_texel`: one level fitted in batches of texels, or texel by
  texel (the seed's loop); `texelbake.stages.cpm.fit_level` chooses by `fit_method`;
- `avis/`: the visible projected area a_vis (§3.4) on cube maps, its closed form, the level
  hierarchy and the Haar-compressed table the renderer reads (`haar`);
- `assemble`: one level as the payload's arrays and its report entry.
"""
