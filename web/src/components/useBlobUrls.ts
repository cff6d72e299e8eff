// Object URLs of a job's preview files, fetched with the bearer token (an <img src> cannot
// send it); revoked when the component goes away.
import { useEffect, useState } from "preact/hooks";
import { fetchBlob, previewUrl } from "../api/client";

export function useBlobUrls(jobId: string, names: string[]): {
  urls: Record<string, string>;
  error: string | null;
} {
  const [urls, setUrls] = useState<Record<string, string>>({});
  const [error, setError] = useState<string | null>(null);
  const key = names.join("|");
  useEffect(() => {
    let alive = true;
    const made: string[] = [];
    (async () => {
      const out: Record<string, string> = {};
      try {
        await Promise.all(
          names.map(async (n) => {
            const u = URL.createObjectURL(await fetchBlob(previewUrl(jobId, n)));
            made.push(u);
            out[n] = u;
          }),
        );
        if (alive) setUrls(out);
      } catch (e) {
        if (alive) setError(`${(e as Error).message}`);
      }
    })();
    return () => {
      alive = false;
      made.forEach((u) => URL.revokeObjectURL(u));
    };
  }, [jobId, key]);
  return { urls, error };
}
