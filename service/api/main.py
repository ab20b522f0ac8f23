"""The ASGI app uvicorn serves (``service.api.main:app``); settings come from the environment."""

from service.api.app import create_app

app = create_app()
