"""The live view in the browser: the trainee's bone, drill and X-rays, and the instructor's page
(``dhg view``, ``dhg-serve --view``; ``docs/viewer.md``)."""

from dhg.view.app import Viewer

__all__ = ["Viewer"]
