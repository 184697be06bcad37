"""The browser viewer: ``GET /`` and ``/viewer`` serve its page, ``/viewer/static/`` its scripts, styles and
the three.js build it loads (vendored from npm, pinned by viewer/package-lock.json; no CDN: users run
air-gapped). The page talks to the same REST API as every other client."""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter, FastAPI
from fastapi.responses import FileResponse, Response
from fastapi.staticfiles import StaticFiles

from bodyfit.api import problems

STATIC = Path(__file__).with_name("viewer")
"""The viewer's static files (package data)."""

router = APIRouter(include_in_schema=False)


@router.api_route("/", methods=["GET", "HEAD"])
@router.api_route("/viewer", methods=["GET", "HEAD"])
def page() -> Response:
    index = STATIC / "index.html"
    if not index.is_file():
        detail = f"this installation has no viewer files ({STATIC}); the API is at /docs"
        return problems.response(problems.problem("not_found", "No viewer", detail, 404))
    # no-cache: the page is small and names the scripts; a stale copy would pair with newer scripts
    return FileResponse(index, headers={"cache-control": "no-cache"})


def install(app: FastAPI) -> None:
    """Serve the viewer on ``app``: its page at / and /viewer, its files under /viewer/static/. An
    installation without the files still serves the API (check_dir=False: no error at start-up)."""
    app.include_router(router)
    app.mount("/viewer/static", StaticFiles(directory=STATIC, check_dir=False), name="viewer")
