# texelbake image shared by the api, the workers and the dashboard (docker-compose.yml).
FROM python:3.11-slim-bookworm AS app
RUN apt-get update && apt-get install -y --no-install-recommends \
        libusb-1.0-0 libgl1 libegl1 libopengl0 libx11-6 libudev1 libidn2-0 libgmp10 libgomp1 \
    && rm -rf /var/lib/apt/lists/*
WORKDIR /app
COPY pyproject.toml README.md ./
COPY texelbake ./texelbake
COPY schemas ./schemas
COPY farm ./farm
COPY texelbake_client ./texelbake_client
COPY services ./services
COPY workers ./workers
COPY scripts ./scripts
RUN pip install --no-cache-dir torch==2.13.0 --index-url https://download.pytorch.org/whl/cpu \
    && pip install --no-cache-dir -e .

# the dashboard's typed client is generated from the API's OpenAPI schema
FROM app AS openapi
RUN python scripts/export_openapi.py /tmp/openapi.json

# the dashboard bundle: npm ci from the lockfile, type-check, vite build (no CDN at run time)
FROM node:20-bookworm-slim AS web
WORKDIR /web
COPY web/package.json web/package-lock.json ./
RUN npm ci --no-audit --no-fund
COPY web/index.html web/vite.config.ts web/tsconfig.json ./
COPY web/src ./src
COPY --from=openapi /tmp/openapi.json ./openapi.json
RUN npm run build

FROM app
COPY --from=web /web/dist ./web/dist
RUN useradd --create-home texelbake && mkdir -p /data && chown texelbake /data
USER texelbake
ENV PYTHONUNBUFFERED=1
