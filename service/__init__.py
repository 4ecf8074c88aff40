"""The RoGUENeRF HTTP service (FastAPI). ``service.app.create_app`` builds the app;
``service.server.run`` serves it with an embedded worker. Nothing heavy runs at import."""
