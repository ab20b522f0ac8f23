"""The ASGI app uvicorn serves (``service.serving.main:app``); settings come from the environment."""

from service.serving.app import create_app

app = create_app()
