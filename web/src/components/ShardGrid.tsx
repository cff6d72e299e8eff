// A stage's shards as a grid of cells coloured by state (a render farm's task view); the
// cell's tooltip holds attempts, worker, time and error.
import type { StagePublic } from "../api/client";

export function ShardGrid({ stage }: { stage: StagePublic }) {
  return (
    <div class="shard-grid" data-testid="shard-grid" data-stage={stage.name}>
      {(stage.shards ?? []).map((s) => (
        <span
          class={`shard state-${s.state}`}
          data-state={s.state}
          title={[
            `${stage.name} shard ${s.shard}: ${s.state}`,
            `attempts ${s.attempts}`,
            s.worker ? `worker ${s.worker}` : "",
            s.seconds != null ? `${s.seconds.toFixed(2)} s` : "",
            s.error ?? "",
          ]
            .filter(Boolean)
            .join("\n")}
        />
      ))}
    </div>
  );
}
