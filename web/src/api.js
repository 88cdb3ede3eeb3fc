// The server's HTTP API as the page uses it: /v1/info, and a request whose events arrive as
// NDJSON lines (one JSON object per line, with a `type` field) read from the fetch body.

/** An error as the API words it: `{"error": {"code", "message"}}` with the HTTP status. */
export class ApiError extends Error {
  constructor(status, code, message) {
    super(message);
    this.status = status;
    this.code = code;
  }

  toString() {
    const status = this.status ? `${this.status} ` : '';
    return `${status}${this.code}: ${this.message}`;
  }
}

export async function serverInfo() {
  const response = await fetch('/v1/info');
  if (!response.ok) throw await errorOf(response);
  return response.json();
}

/**
 * Sends `body` to `path` (with the options as query parameters) and calls `onEvent` with each
 * streamed event (`progress`, `face`, then `done`). Resolves with the `done` event; rejects with
 * an ApiError for a refused request or an `error` event, and with an AbortError when `signal`
 * aborts (the server then cancels the request: it sees the connection close).
 */
export async function streamRequest({ path, body, contentType, options, signal, onEvent }) {
  const query = new URLSearchParams();
  for (const [name, value] of Object.entries(options)) {
    if (value !== '' && value !== undefined) query.set(name, value);
  }
  const response = await fetch(`${path}?${query}`, {
    method: 'POST',
    headers: { 'content-type': contentType, accept: 'application/x-ndjson' },
    body,
    signal,
  });
  if (!response.ok) throw await errorOf(response);
  const reader = response.body.pipeThrough(new TextDecoderStream()).getReader();
  let buffered = '';
  for (;;) {
    const { value, done } = await reader.read();
    if (done) break;
    buffered += value;
    let end;
    while ((end = buffered.indexOf('\n')) >= 0) {
      const line = buffered.slice(0, end).trim();
      buffered = buffered.slice(end + 1);
      if (!line) continue;
      const event = JSON.parse(line);
      if (event.type === 'error') throw new ApiError(0, event.error.code, event.error.message);
      onEvent(event);
      if (event.type === 'done') return event;
    }
  }
  throw new ApiError(0, 'stream_ended', 'the stream ended before its last event');
}

/** The API's error from a refused request's body, or the status line when it has none. */
async function errorOf(response) {
  const text = await response.text();
  try {
    const { error } = JSON.parse(text);
    return new ApiError(response.status, error.code, error.message);
  } catch {
    return new ApiError(response.status, 'http_error', text || response.statusText);
  }
}
