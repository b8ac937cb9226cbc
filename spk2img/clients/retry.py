"""When to try a request again, and after how long: the one retry policy of both clients."""

from __future__ import annotations

from dataclasses import dataclass

from .errors import ConnectionFailed, Spk2ImgError, Unavailable


@dataclass(frozen=True)
class RetryPolicy:
    """Bounded exponential backoff for failures that a later attempt may not meet.

    Only :class:`~spk2img.clients.errors.ConnectionFailed` and
    :class:`~spk2img.clients.errors.Unavailable` are retried, at most ``retries`` times after the
    first attempt. Attempt ``n`` (0-based) failing waits ``backoff * 2**n`` seconds, or the
    server's ``Retry-After`` when it sent one, and never more than ``max_delay`` seconds.
    """

    retries: int = 3
    backoff: float = 0.5
    max_delay: float = 30.0

    def __post_init__(self):
        if self.retries < 0 or self.backoff < 0 or self.max_delay < 0:
            raise ValueError(f"retries, backoff and max_delay must be >= 0, got {self}")

    def delay(self, attempt: int, error: Spk2ImgError) -> float | None:
        """Seconds to wait before trying again after attempt ``attempt`` (0-based) failed with
        ``error``, or ``None`` to give up and raise it."""
        if attempt >= self.retries or not isinstance(error, ConnectionFailed | Unavailable):
            return None
        hint = error.retry_after if isinstance(error, Unavailable) else None
        wait = self.backoff * 2**attempt if hint is None else hint
        return min(wait, self.max_delay)
