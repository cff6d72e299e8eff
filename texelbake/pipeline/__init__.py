"""Which stages an asset needs (`plan`) and running them (`run`: one shard, or the whole
bake in this process), the bake's running estimate (`estimate`) and a bake process's set-up
(`process`)."""
