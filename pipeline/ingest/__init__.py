"""Bringing user data in: import (scans in any format), merge-brackets (LDR brackets into an HDR photo)."""
