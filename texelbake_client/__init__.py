"""The HTTP clients of the texelbake API (httpx and the standard library, no server imports):
`submit` (one asset: upload, follow, download; `texelbake submit FILE`) and `batch` (many
assets as one batch; `texelbake submit --manifest FILE`). The Blender add-on speaks the same
API with its own stdlib client (blender/texelbake_submit/client.py)."""
