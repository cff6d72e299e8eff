"""The batched path of the CPM fit: many texels' points from their Gram matrices.

Modules: `fit` (`fit_many`, one texel's fit from its Grams, a wide texel by batches),
`linalg` (stacked eigendecompositions, top eigenpairs, the reduced systems of the trials),
`identical` (candidates with identical columns fitted as one), `columns` (a wide texel's F
read a block of columns at a time). The search on c and a texel's result are shared with the
per-texel path (`texelbake.cpm.search`, `texelbake.cpm.texel_fit`).
"""
