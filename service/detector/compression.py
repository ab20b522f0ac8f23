"""Compressed copies of an ONNX model, made with onnxruntime's own tools (they need the ``onnx``
package: the ``optimize`` extra): int8 static quantization, its activation ranges read from real
input batches, and float16 for GPU providers."""

from __future__ import annotations

import tempfile
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from service.errors import InvalidInput


@dataclass(frozen=True)
class Int8Choices:
    """Which weights get a scale per output channel, and which nodes stay float: chosen by
    measurement on the bundled model (docs/variants.md, ``python -m benchmarks.quantization_choices``)."""

    per_channel: bool = True
    float_first_and_last: bool = False  # the node reading the image and the node writing the heatmaps


def quantize_int8(
    source: Path,
    target: Path,
    input_name: str,
    batches: Iterable[np.ndarray],
    choices: Int8Choices = Int8Choices(),
) -> None:
    """Static int8 quantization (QDQ: int8 weights, uint8 activations with MinMax ranges of ``batches``)."""
    quantization = _onnx_tools()
    with tempfile.TemporaryDirectory() as scratch:
        prepared = Path(scratch) / "prepared.onnx"
        quantization.quant_pre_process(str(source), str(prepared))  # shapes inferred, graph optimized
        quantization.quantize_static(
            str(prepared),
            str(target),
            _Batches(input_name, iter(batches)),
            quant_format=quantization.QuantFormat.QDQ,
            per_channel=choices.per_channel,
            activation_type=quantization.QuantType.QUInt8,
            weight_type=quantization.QuantType.QInt8,
            nodes_to_exclude=_first_and_last(prepared) if choices.float_first_and_last else None,
            calibrate_method=quantization.CalibrationMethod.MinMax,
        )


def convert_float16(source: Path, target: Path) -> None:
    """Weights and arithmetic in float16; the input and output stay float32, as the manifest says."""
    _onnx_tools()
    import onnx
    from onnxruntime.transformers.float16 import convert_float_to_float16

    onnx.save(convert_float_to_float16(onnx.load(str(source)), keep_io_types=True), str(target))


class _Batches:
    """onnxruntime's CalibrationDataReader protocol over input batches."""

    def __init__(self, input_name: str, batches: Iterator[np.ndarray]) -> None:
        self._input_name, self._batches = input_name, batches

    def get_next(self) -> dict[str, np.ndarray] | None:
        batch = next(self._batches, None)
        return None if batch is None else {self._input_name: batch}


def _first_and_last(model_path: Path) -> list[str]:
    import onnx

    graph = onnx.load(str(model_path)).graph
    inputs, outputs = {i.name for i in graph.input}, {o.name for o in graph.output}
    return [n.name for n in graph.node if inputs & set(n.input) or outputs & set(n.output)]


def _onnx_tools():  # noqa: ANN202 (a module)
    try:
        import onnx  # noqa: F401  (onnxruntime's quantization tools need it)
        from onnxruntime import quantization
    except ImportError:
        raise InvalidInput(
            "optimize needs the onnx package: pip install 'conformal-keypoint-service[optimize]'"
        ) from None
    return quantization
