"""The service tests' sample fixtures, shared with the deployment tests."""

from tests.service.conftest import coco, model_path, samples_dir  # noqa: F401
