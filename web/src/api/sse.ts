// Server-sent events over fetch: EventSource cannot send the bearer token, so the stream is
// read with fetch and parsed here (`id:`, `event:`, `data:`, blank line). A stream the server
// closed is reopened with Last-Event-ID until `done()` says the subject is finished.
import { getToken } from "./client";

export interface SseMessage {
  id: string | null;
  event: string;
  data: string;
}

export interface SseOptions {
  onMessage: (m: SseMessage) => void;
  /** true when no reconnect is wanted after the server closed the stream */
  done?: () => boolean;
  onError?: (e: unknown) => void;
}

export function parseSse(buffer: string): { messages: SseMessage[]; rest: string } {
  const messages: SseMessage[] = [];
  const blocks = buffer.split(/\r?\n\r?\n/);
  const rest = blocks.pop() ?? "";
  for (const block of blocks) {
    let id: string | null = null;
    let event = "message";
    const data: string[] = [];
    for (const line of block.split(/\r?\n/)) {
      if (!line || line.startsWith(":")) continue;
      const i = line.indexOf(":");
      const field = i < 0 ? line : line.slice(0, i);
      const value = i < 0 ? "" : line.slice(i + 1).replace(/^ /, "");
      if (field === "id") id = value;
      else if (field === "event") event = value;
      else if (field === "data") data.push(value);
    }
    if (data.length) messages.push({ id, event, data: data.join("\n") });
  }
  return { messages, rest };
}

/** Open an events stream; returns a function that closes it. */
export function openEvents(url: string, opts: SseOptions): () => void {
  const ctrl = new AbortController();
  let lastId: string | null = null;
  let closed = false;

  async function once(): Promise<void> {
    const headers: Record<string, string> = { Accept: "text/event-stream" };
    const token = getToken();
    if (token) headers.Authorization = `Bearer ${token}`;
    if (lastId) headers["Last-Event-ID"] = lastId;
    const r = await fetch(url, { headers, signal: ctrl.signal });
    if (!r.ok || !r.body) throw new Error(`events: HTTP ${r.status}`);
    const reader = r.body.pipeThrough(new TextDecoderStream()).getReader();
    let buf = "";
    for (;;) {
      const { value, done } = await reader.read();
      if (done) return;
      buf += value;
      const { messages, rest } = parseSse(buf);
      buf = rest;
      for (const m of messages) {
        if (m.id) lastId = m.id;
        opts.onMessage(m);
      }
    }
  }

  (async () => {
    let failures = 0;
    while (!closed) {
      try {
        await once();
        failures = 0;
      } catch (e) {
        if (closed) return;
        failures += 1;
        opts.onError?.(e);
        if (failures >= 5) return;
      }
      if (closed || opts.done?.()) return;
      await new Promise((res) => setTimeout(res, Math.min(5000, 250 * 2 ** failures)));
    }
  })();

  return () => {
    closed = true;
    ctrl.abort();
  };
}
