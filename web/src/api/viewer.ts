// The viewer data of a finished job (`/jobs/{id}/viewer`, services/viewer_data.py): the
// manifest, float32 arrays and the texel table.
import { api, errorText, fetchBlob } from "./client";

export interface LodInfo {
  file: string;
  faces: number;
  vertices: number;
  bounds: [number[], number[]];
}

export interface ArrayRef {
  file: string;
  shape: number[];
}

export interface BtfInfo {
  n_components: [number, number, number];
  channels: number;
  top_level: number;
  levels: [number, number][];
  weight_offsets: [number, number][];
  weights: ArrayRef;
  eigen: ArrayRef;
  lut: ArrayRef;
  pair_index: ArrayRef;
  mean_table: ArrayRef;
  num_pairs: number;
  mean_models: string[];
  mean_params: number[][];
  rgb_from_ycbcr: number[][];
  grazing_cos: number;
}

export interface Manifest {
  name: string;
  atlas: number;
  levels: number;
  lods: LodInfo[];
  avis: { file: string; n_theta: number; n_phi: number; theta_max_deg: number; unit: string };
  frames: string;
  btf: BtfInfo | null;
}

export interface Texels {
  n: number;
  points: number[];
  k: number[];
  snr_heldout_db: (number | null)[];
  snr_insample_db: (number | null)[];
  valid: boolean[];
}

export function viewerFileUrl(jobId: string, name: string): string {
  return `/api/v1/jobs/${encodeURIComponent(jobId)}/viewer/${encodeURIComponent(name)}`;
}

export async function loadManifest(jobId: string): Promise<Manifest> {
  const { data, error, response } = await api.GET("/api/v1/jobs/{job_id}/viewer", {
    params: { path: { job_id: jobId } },
  });
  if (error || !data) throw new Error(errorText(error, response.status));
  return data as unknown as Manifest;
}

export async function loadF32(jobId: string, name: string): Promise<Float32Array> {
  const blob = await fetchBlob(viewerFileUrl(jobId, name));
  return new Float32Array(await blob.arrayBuffer());
}

export async function loadTexels(jobId: string): Promise<Texels> {
  const blob = await fetchBlob(viewerFileUrl(jobId, "texels.json"));
  return JSON.parse(await blob.text());
}

export async function loadImage(jobId: string, name: string): Promise<ImageBitmap> {
  const blob = await fetchBlob(viewerFileUrl(jobId, name));
  return createImageBitmap(blob, { imageOrientation: "none", premultiplyAlpha: "none", colorSpaceConversion: "none" });
}
