"""The robot side of the service: `RobotClient` streams a sensor source to the hapticlink service.

Split by job: client.py (the run loop, source → resend buffer, acknowledgements), session.py
(opening a session with the fleet API key), resend.py (the resend buffer), outbox.py (what the client
and its transports share: buffer, frame queue, acknowledgements, counters, backoffs), ws.py and http.py (the
two block transports), frames.py (camera frames), backoff.py (waiting between attempts), errors.py.
The wire protocol they speak is drivers/protocol.py.
"""

from drivers.robot.backoff import Backoff
from drivers.robot.client import RobotClient, RobotStats
from drivers.robot.errors import RobotAuthError, ServiceRefused, ServiceUnavailable, SessionLostError
from drivers.robot.outbox import Endpoint, Outbox
from drivers.robot.resend import Pending, ResendBuffer
from drivers.robot.session import SessionInfo, open_session

__all__ = [
    "Backoff",
    "Endpoint",
    "Outbox",
    "Pending",
    "ResendBuffer",
    "RobotAuthError",
    "RobotClient",
    "RobotStats",
    "ServiceRefused",
    "ServiceUnavailable",
    "SessionInfo",
    "SessionLostError",
    "open_session",
]
