"""The streaming reconstruction service (FastAPI): build it with
:func:`spk2img.service.app.create_app`, run it with ``spk2img serve``; see docs/service.md."""
