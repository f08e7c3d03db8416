"""Google Compute Engine backend (google-cloud-compute, Application Default Credentials).

The SDK is imported when the provider is constructed, never at `ccrp` start-up (~1.5 s)."""

from .provider import GcpProvider

__all__ = ["GcpProvider"]
