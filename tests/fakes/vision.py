"""A local endpoint speaking Google Cloud Vision's REST API (v1 images:annotate) and the OAuth
token exchange of a service-account key, for the API manager's google-vision backend.

It answers every image with one face and one label; `fail` queues failures to serve first, one a
request: an HTTP status (503 outage, 429 quota) or "hang" (no answer for `hang_s`: a timeout).
"""

from __future__ import annotations

import base64
import json
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import padding
from cryptography.hazmat.primitives.asymmetric import rsa

TYPES = {1: "FACE_DETECTION", 4: "LABEL_DETECTION", 19: "OBJECT_LOCALIZATION"}
FACE = {"boundingPoly": {"vertices": [{"x": 97, "y": 64}, {"x": 237, "y": 64}, {"x": 237, "y": 204}, {"x": 97, "y": 204}]},
        "detectionConfidence": 0.93}
LABELS = [{"mid": "/m/0dzct", "description": "Face", "score": 0.97}, {"mid": "/m/01g317", "description": "Person", "score": 0.41}]


class FakeVision:
    def __init__(self, host: str = "127.0.0.1", port: int = 0, hang_s: float = 3.0) -> None:
        self.fail: list = []
        self.keys: dict[str, object] = {}  # client_email -> public key of the service accounts made
        self.jwts = 0  # calls authorized by a self-signed JWT (what the client sends for a service account)
        self.requests: list[dict] = []  # the annotate requests served (decoded JSON)
        self.tokens = 0
        self.hang_s = hang_s
        self.lock = threading.Lock()
        fake = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *args) -> None:
                pass

            def _send(self, code: int, body: dict) -> None:
                data = json.dumps(body).encode()
                try:
                    self.send_response(code)
                    self.send_header("Content-Type", "application/json")
                    self.send_header("Content-Length", str(len(data)))
                    self.end_headers()
                    self.wfile.write(data)
                except (BrokenPipeError, ConnectionResetError):
                    pass  # the client gave up waiting (a "hang" failure)

            def do_POST(self) -> None:  # noqa: N802 - http.server's name
                body = self.rfile.read(int(self.headers.get("Content-Length", 0)))
                if self.path == "/token":
                    with fake.lock:
                        fake.tokens += 1
                    return self._send(200, {"access_token": "fake-token", "expires_in": 3600, "token_type": "Bearer"})
                if self.path.split("?")[0] != "/v1/images:annotate":
                    return self._send(404, {"error": {"code": 404, "message": "not found", "status": "NOT_FOUND"}})
                if not fake.authorized(self.headers.get("Authorization", "")):
                    return self._send(401, {"error": {"code": 401, "message": "no token", "status": "UNAUTHENTICATED"}})
                with fake.lock:
                    failure = fake.fail.pop(0) if fake.fail else None
                if failure == "hang":
                    time.sleep(fake.hang_s)
                    return self._send(503, {"error": {"code": 503, "message": "late", "status": "UNAVAILABLE"}})
                if failure is not None:
                    status = {429: "RESOURCE_EXHAUSTED", 503: "UNAVAILABLE"}.get(failure, "INTERNAL")
                    return self._send(failure, {"error": {"code": failure, "message": f"fake {status}", "status": status}})
                req = json.loads(body)
                with fake.lock:
                    fake.requests.append(req)
                responses = []
                for r in req["requests"]:
                    base64.b64decode(r["image"]["content"])  # the image must be there
                    # Feature.Type by name, or by number (the client's REST transport sends numbers).
                    kinds = {TYPES.get(f.get("type"), f.get("type")) for f in r.get("features", [])}
                    resp: dict = {}
                    if "FACE_DETECTION" in kinds:
                        resp["faceAnnotations"] = [FACE]
                    if "LABEL_DETECTION" in kinds:
                        resp["labelAnnotations"] = LABELS
                    responses.append(resp)
                self._send(200, {"responses": responses})

        self.server = ThreadingHTTPServer((host, port), Handler)
        self.server.daemon_threads = True
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)

    def authorized(self, header: str) -> bool:
        """A token from /token, or a JWT self-signed by a service-account key made here (google-auth
        sends that, not a token, when the client asks for its default scopes)."""
        scheme, _, token = header.partition(" ")
        if scheme != "Bearer":
            return False
        if token == "fake-token":
            return True
        try:
            head, body, sig = token.split(".")
            claims = json.loads(base64.urlsafe_b64decode(body + "=" * (-len(body) % 4)))
            key = self.keys[claims["iss"]]
            key.verify(base64.urlsafe_b64decode(sig + "=" * (-len(sig) % 4)), f"{head}.{body}".encode(),
                       padding.PKCS1v15(), hashes.SHA256())
        except (ValueError, KeyError, InvalidSignature):
            return False
        if claims.get("exp", 0) < time.time():
            return False
        with self.lock:
            self.jwts += 1
        return True

    @property
    def url(self) -> str:
        host, port = self.server.server_address[:2]
        return f"http://{host}:{port}"

    def __enter__(self) -> "FakeVision":
        self.thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self.server.shutdown()
        self.server.server_close()

    def service_account(self, token_uri: str | None = None) -> dict:
        """A service-account key whose token exchange this endpoint answers."""
        key = rsa.generate_private_key(public_exponent=65537, key_size=2048)
        pem = key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                serialization.NoEncryption()).decode()
        email = f"ccrp{len(self.keys)}@ccrp-test.iam.gserviceaccount.com"
        self.keys[email] = key.public_key()
        return {"type": "service_account", "project_id": "ccrp-test", "private_key_id": "k1", "private_key": pem,
                "client_email": email, "client_id": "1",
                "token_uri": token_uri or f"{self.url}/token"}
