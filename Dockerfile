# texelbake image shared by the api, the workers and the dashboard (docker-compose.yml).
FROM python:3.11-slim-bookworm
RUN apt-get update && apt-get install -y --no-install-recommends \
        libusb-1.0-0 libgl1 libegl1 libopengl0 libx11-6 libudev1 libidn2-0 libgmp10 libgomp1 \
    && rm -rf /var/lib/apt/lists/*
WORKDIR /app
COPY pyproject.toml README.md ./
COPY texelbake ./texelbake
COPY schemas ./schemas
COPY services ./services
COPY workers ./workers
COPY web ./web
RUN pip install --no-cache-dir torch==2.13.0 --index-url https://download.pytorch.org/whl/cpu \
    && pip install --no-cache-dir -e .
RUN useradd --create-home texelbake && mkdir -p /data && chown texelbake /data
USER texelbake
ENV PYTHONUNBUFFERED=1
