# The conformal keypoint service with the bundled default model and calibration.

# Build stage: a wheel with the compiled anchor-median kernel (needs a C compiler).
FROM python:3.11-bookworm AS build
WORKDIR /src
COPY pyproject.toml README.md ./
COPY service ./service
COPY calibration_store ./calibration_store
COPY client ./client
RUN pip wheel --no-deps --wheel-dir /wheels . \
    && python -m zipfile -l /wheels/*.whl | grep -q _upper_half  # the kernel was compiled

FROM python:3.11-slim-bookworm

ENV PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    CKS_HOST=0.0.0.0 \
    CKS_PORT=8000 \
    CKS_DATA_DIR=/data \
    CKS_MODEL_DIR=/app/models/lmo-synth-unet

WORKDIR /app
COPY --from=build /wheels /wheels
RUN pip install "$(ls /wheels/*.whl)[postgres]" && rm -rf /wheels \
    && python -c "from service.conformal.kernel import native_kernel_available as ok; assert ok()" \
    && useradd --system --uid 10001 --no-create-home --shell /usr/sbin/nologin app \
    && mkdir -p /data && chown app /data
COPY models/lmo-synth-unet ./models/lmo-synth-unet

USER app
VOLUME /data
EXPOSE 8000
HEALTHCHECK --interval=10s --timeout=3s --start-period=30s --retries=3 \
    CMD python -c "import urllib.request; urllib.request.urlopen('http://127.0.0.1:8000/readyz', timeout=2)"
CMD ["keypoint-service", "serve"]
