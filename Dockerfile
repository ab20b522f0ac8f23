# The conformal keypoint service with the bundled default model and calibration.
#
#   docker build -t keypoint-service .                    # CPU: the default target (the last stage)
#   docker build --target cuda -t keypoint-service:cuda .  # NVIDIA GPU: onnxruntime-gpu (docs/operations.md)
#   docker run --gpus all -p 8000:8000 keypoint-service:cuda

# The CUDA target's base: its CUDA and cuDNN must be those the onnxruntime-gpu release wants
# (onnxruntime.ai/docs/execution-providers/CUDA-ExecutionProvider.html#requirements): 1.31
# links CUDA 13 (libcublas.so.13) and asks for cuDNN 9. The build fails when they differ.
ARG CUDA_IMAGE=nvidia/cuda:13.0.0-cudnn-runtime-ubuntu22.04

# Build stage: a wheel with the compiled JPEG windows (a C compiler and libjpeg's headers: both in
# this image).
FROM python:3.11-bookworm AS build
WORKDIR /src
COPY pyproject.toml README.md ./
COPY service ./service
COPY calibration_store ./calibration_store
COPY client ./client
RUN pip wheel --no-deps --wheel-dir /wheels . \
    && python -m zipfile -l /wheels/*.whl | grep -q _jpeg_window  # it was compiled

# ---- CUDA target (--target cuda): never built for the default target, which is the last stage.
FROM ${CUDA_IMAGE} AS cuda-python
ENV DEBIAN_FRONTEND=noninteractive \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    VIRTUAL_ENV=/opt/venv \
    PATH=/opt/venv/bin:$PATH
RUN apt-get update && apt-get install -y --no-install-recommends python3.11 python3.11-venv \
    && rm -rf /var/lib/apt/lists/* && python3.11 -m venv /opt/venv

# The wheel is compiled against this image's Python and C library, not the CPU stages'.
FROM cuda-python AS cuda-build
RUN apt-get update && apt-get install -y --no-install-recommends gcc libc6-dev python3.11-dev \
        libjpeg-turbo8-dev \
    && rm -rf /var/lib/apt/lists/*
WORKDIR /src
COPY pyproject.toml README.md ./
COPY service ./service
COPY calibration_store ./calibration_store
COPY client ./client
RUN pip wheel --no-deps --wheel-dir /wheels . \
    && python -m zipfile -l /wheels/*.whl | grep -q _jpeg_window

FROM cuda-python AS cuda
# Measured on an H200 (docs/operations.md, Serving from a GPU): the CPU work, not the model, is
# the bottleneck, so several workers (about half the host's cores: -e CKS_WORKERS=N) serve the most.
ENV PYTHONUNBUFFERED=1 \
    CKS_HOST=0.0.0.0 \
    CKS_PORT=8000 \
    CKS_DATA_DIR=/data \
    CKS_MODEL_DIR=/app/models/lmo-synth-unet \
    CKS_EXECUTION_PROVIDERS=CUDAExecutionProvider,CPUExecutionProvider \
    CKS_WORKERS=4 \
    CKS_MAX_CONCURRENT_INFERENCES=16
WORKDIR /app
COPY --from=cuda-build /wheels /wheels
# onnxruntime-gpu replaces onnxruntime: both own the `onnxruntime` module, so the CPU build is
# removed and the GPU build's files put back (the uninstall took the files the two share).
# Then every library the CUDA provider links must be in the image, but the driver's libcuda
# (mounted by --gpus): otherwise onnxruntime would fall back to the CPU at start-up.
RUN apt-get update && apt-get install -y --no-install-recommends libjpeg-turbo8 \
    && rm -rf /var/lib/apt/lists/* \
    && pip install "$(ls /wheels/*.whl)[postgres,gpu]" && rm -rf /wheels \
    && pip uninstall -y onnxruntime \
    && pip install --force-reinstall --no-deps "onnxruntime-gpu>=1.17" \
    && python -c "import onnxruntime as o; assert 'CUDAExecutionProvider' in o.get_available_providers()" \
    && ! ldd "$(python -c "import onnxruntime as o, pathlib; print(pathlib.Path(o.__file__).parent \
         / 'capi' / 'libonnxruntime_providers_cuda.so')")" | grep "not found" | grep -v "libcuda\.so\.1" \
    && python -c "from service.detector.images import jpeg_windows_available as ok; assert ok()" \
    && useradd --system --uid 10001 --no-create-home --shell /usr/sbin/nologin app \
    && mkdir -p /data && chown app /data
COPY models/lmo-synth-unet ./models/lmo-synth-unet

USER app
VOLUME /data
EXPOSE 8000
HEALTHCHECK --interval=10s --timeout=3s --start-period=60s --retries=3 \
    CMD python -c "import urllib.request; urllib.request.urlopen('http://127.0.0.1:8000/readyz', timeout=2)"
CMD ["keypoint-service", "serve"]

# ---- CPU: the default target (keep it the last stage).
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
# libjpeg-turbo's runtime for the JPEG windows (service/detector/native/jpeg_window.c).
RUN apt-get update && apt-get install -y --no-install-recommends libjpeg62-turbo \
    && rm -rf /var/lib/apt/lists/* \
    && pip install "$(ls /wheels/*.whl)[postgres]" && rm -rf /wheels \
    && python -c "from service.detector.images import jpeg_windows_available as ok; assert ok()" \
    && useradd --system --uid 10001 --no-create-home --shell /usr/sbin/nologin app \
    && mkdir -p /data && chown app /data
COPY models/lmo-synth-unet ./models/lmo-synth-unet
# The faster int8 variant: -e CKS_MODEL_DIR=/app/models/lmo-synth-unet-int8 (docs/variants.md).
COPY models/lmo-synth-unet-int8 ./models/lmo-synth-unet-int8

USER app
VOLUME /data
EXPOSE 8000
HEALTHCHECK --interval=10s --timeout=3s --start-period=30s --retries=3 \
    CMD python -c "import urllib.request; urllib.request.urlopen('http://127.0.0.1:8000/readyz', timeout=2)"
CMD ["keypoint-service", "serve"]
