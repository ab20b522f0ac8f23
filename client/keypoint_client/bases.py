"""What the generated models (generated_models.py) inherit beyond their fields: immutability,
the API's JSON form, numpy arrays as input, and a few conveniences. The fields come from
openapi/openapi.json; those named here under TYPE_CHECKING are the ones a method reads."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Self

from pydantic import BaseModel, ConfigDict, SerializerFunctionWrapHandler, model_serializer, model_validator

if TYPE_CHECKING:
    from keypoint_client.generated_models import ActivationOut, Manifest

FINISHED: frozenset[str] = frozenset({"succeeded", "failed", "interrupted"})


class Frozen(BaseModel):
    """An immutable body of the API; ``to_dict()`` is its JSON form."""

    model_config = ConfigDict(frozen=True)

    def to_dict(self) -> dict[str, Any]:
        return self.model_dump(mode="json")

    @model_serializer(mode="wrap")
    def _as_the_api_writes_it(self, handler: SerializerFunctionWrapHandler) -> dict[str, Any]:
        """A member the API leaves out when it has no value (``pose``, ``prediction_id``) stays out."""
        data: dict[str, Any] = handler(self)
        return {
            key: value for key, value in data.items() if value is not None or key in self.model_fields_set
        }


class TakesArrays(Frozen):
    """A request whose matrices and vectors may be numpy arrays (read as nested lists)."""

    @model_validator(mode="before")
    @classmethod
    def _arrays_as_lists(cls, data: Any) -> Any:
        if not isinstance(data, dict):
            return data
        return {key: value.tolist() if hasattr(value, "tolist") else value for key, value in data.items()}


class PoseRequestBase(TakesArrays):
    @classmethod
    def pinhole(cls, fx: float, fy: float, cx: float, cy: float, **options: Any) -> Self:
        """The request for the camera with these intrinsics (no skew); ``options`` as the fields."""
        return cls.model_validate({"K": ((fx, 0.0, cx), (0.0, fy, cy), (0.0, 0.0, 1.0)), **options})


class GuaranteeBase(Frozen):
    if TYPE_CHECKING:
        t: int

    @property
    def bounded(self) -> bool:
        """Whether the set is finite (t > 0)."""
        return self.t > 0


class ModelInfoBase(Frozen):
    if TYPE_CHECKING:
        manifest: Manifest

    @property
    def object_names(self) -> list[str]:
        return [entry.name for entry in self.manifest.objects]

    @property
    def keypoint_names(self) -> list[str]:
        return [entry.name for entry in self.manifest.keypoints]


class JobBase(Frozen):
    if TYPE_CHECKING:
        state: str

    @property
    def finished(self) -> bool:
        return self.state in FINISHED


class ActivationLogBase(Frozen):
    if TYPE_CHECKING:
        active_version: int | None
        activations: list[ActivationOut]

    def previous_version(self) -> int:
        """The version active before the current one: what a rollback goes back to."""
        for entry in reversed(self.activations):
            if entry.version != self.active_version:
                return entry.version
        raise ValueError(
            f"no version other than {self.active_version} was ever active: nothing to roll back to"
        )
