"""What studio bakers make today, baked from M_org onto M1: albedo and tangent-space
normal maps (`normal_maps`), and per mip level the filtered maps of Toksvig and LEADR with AO
(`filtered_maps`)."""
