"""``report.pdf``: the report's sections and figures typeset on A4 by Typst
(``reporting.typeset``: the engine, and why), on every machine, from the same content model and
SVGs as ``report.html``.

The PDF is kept under ``out/artifacts/figures`` by the digest of what it is made of (the
document, the figures' SVGs, the Typst version) and reused when a rebuild changes none of it.
Should Typst fail, no PDF is written, an older ``report.pdf`` is removed (never left looking
current) and the outcome's message says why.
"""

from __future__ import annotations

import hashlib
import io
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

from pypdf import PdfReader

from pipeline.io.artifacts import atomic_save
from pipeline.io.files import ARTIFACT_MAX_BYTES, FileRefused, is_regular, read_bytes, unlink
from pipeline.reporting.content import Section
from pipeline.reporting.figure_cache import FigureStore, digest_of
from pipeline.reporting.typeset import ENGINE, TypesetError, document_inputs, typeset


@dataclass(frozen=True, kw_only=True)
class PdfOutcome:
    """``path``: the PDF written (None: none, see ``message``); ``pages``: its page count."""

    path: Path | None
    pages: int
    reused: bool
    message: str


def write_pdf(
    store: FigureStore,
    target: Path,
    *,
    title: str,
    subtitle: str,
    sections: Sequence[Section],
    colophon: str,
) -> PdfOutcome:
    """Typeset ``sections`` (their figures' SVGs read from ``store.svgs``) into ``target``, or
    reuse the PDF kept for the same inputs (read without following a link; a kept file that is
    not a regular file is typeset again and replaced); ``colophon``: the closing line."""
    inputs = document_inputs(title, subtitle, sections, colophon, store.svgs)
    kept = store.pdf_file(digest_of("pdf", ENGINE, _digests(inputs)))
    reused = is_regular(kept)
    try:
        if reused:
            content = read_bytes(kept, ARTIFACT_MAX_BYTES)
        else:
            content = typeset(inputs)
            atomic_save(kept, lambda stream: stream.write(content), ".pdf", cache=True)
        atomic_save(target, lambda stream: stream.write(content), ".pdf")
    except (OSError, FileRefused, TypesetError) as error:
        unlink(target)
        unlink(kept)
        return PdfOutcome(
            path=None, pages=0, reused=False, message=f"report.pdf not written: {error}"
        )
    pages = len(PdfReader(io.BytesIO(content)).pages)
    return PdfOutcome(
        path=target,
        pages=pages,
        reused=reused,
        message=f"report.pdf ({pages} pages{', reused' if reused else ''})",
    )


def _digests(inputs: Mapping[str, str]) -> dict[str, str]:
    """SHA-256 of each input (the SVGs are large: their digests go into the PDF's)."""
    return {name: hashlib.sha256(text.encode()).hexdigest() for name, text in inputs.items()}
