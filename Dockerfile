# RoGUENeRF service image: the API (default command) and the worker (python -m workers).
#
# CPU build (default):   docker build -t roguenerf .
# CUDA build:            docker build -t roguenerf:cu128 \
#                          --build-arg TORCH_INDEX_URL=https://download.pytorch.org/whl/cu128 .
# (see docs/service.md; run the worker with --gpus all)
ARG PYTHON_VERSION=3.11
FROM python:${PYTHON_VERSION}-slim

ARG TORCH_VERSION=2.13.0
ARG TORCH_INDEX_URL=https://download.pytorch.org/whl/cpu
# Extra pip packages (the image already has psycopg for a PostgreSQL job table).
ARG EXTRA_PIP=""

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1

# gcc: the inference fast path compiles its fused C kernels (roguenerf/native) on first use,
# for the CPU it runs on; without a compiler it falls back to slower torch code.
RUN apt-get update \
    && apt-get install -y --no-install-recommends gcc libc6-dev \
    && rm -rf /var/lib/apt/lists/*

# torch first, from the chosen index, so the package install below never pulls a CUDA build.
RUN pip install "torch==${TORCH_VERSION}" --index-url "${TORCH_INDEX_URL}"

WORKDIR /app
COPY pyproject.toml README.md ./
COPY roguenerf ./roguenerf
COPY jobs ./jobs
COPY service ./service
COPY workers ./workers
COPY roguecli ./roguecli
RUN pip install ".[service,postgresql]" ${EXTRA_PIP}

RUN useradd --create-home --uid 10001 roguenerf \
    && mkdir -p /data && chown roguenerf:roguenerf /data
USER roguenerf
# API and worker share the host's cores: OpenMP threads sleep instead of spinning while they
# wait (roguenerf/runtime.py, bench/threads.py; `roguenerf serve` sets the same).
ENV ROGUENERF_DATA_DIR=/data \
    OMP_WAIT_POLICY=PASSIVE
VOLUME ["/data"]
EXPOSE 8000

HEALTHCHECK --interval=30s --timeout=5s --start-period=60s \
  CMD python -c "import urllib.request; urllib.request.urlopen('http://127.0.0.1:8000/healthz', timeout=4)"

CMD ["uvicorn", "--factory", "service.app:create_app", "--host", "0.0.0.0", "--port", "8000"]
