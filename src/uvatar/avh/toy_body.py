"""Re-export of the toy tube body (it lives in :mod:`uvatar.body.toy`; its default is AVH's 6-joint tube)."""

from uvatar.body.toy import ToyTubeBody  # noqa: F401
