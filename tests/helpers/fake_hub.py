"""A local stand-in for the Hugging Face Hub's HTTP API, for tests without network.

It implements the few endpoints that `LeRobotDataset.push_to_hub` and a
`LeRobotDataset` download call through huggingface_hub: create a repo, preupload
and commit files (always "regular" uploads, inline base64, so no LFS/Xet), tags,
refs, repo info and file resolution. Files live in memory; a tag freezes a copy.
`FakeHub.route_all_hub_traffic()` sends every request huggingface_hub makes (its
endpoint and the hard-coded https://huggingface.co/api/validate-yaml of card pushes)
to the stand-in, through huggingface_hub's own `set_client_factory` hook.
"""

from __future__ import annotations

import base64
import hashlib
import json
import re
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from urllib.parse import unquote, urlparse

import httpx
from huggingface_hub import close_session, set_client_factory
from huggingface_hub.utils._http import default_client_factory

PUBLIC_URL = "https://huggingface.co"  # what the real Hub puts in the URLs it returns


class FakeHub:
    def __init__(self) -> None:
        self.repos: dict[str, dict] = {}  # repo_id -> {"main"|"tags"|"commits": snapshots of {path: bytes}}
        self.requests: list[str] = []
        self._server = ThreadingHTTPServer(("127.0.0.1", 0), self._handler())
        self.url = f"http://127.0.0.1:{self._server.server_address[1]}"
        self._thread = threading.Thread(target=self._server.serve_forever, daemon=True)

    def __enter__(self) -> FakeHub:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        set_client_factory(default_client_factory)
        close_session()
        self._server.shutdown()
        self._server.server_close()

    def route_all_hub_traffic(self) -> None:
        """Make huggingface_hub's shared HTTP client deliver every request here."""
        target = httpx.URL(self.url)

        class ToFakeHub(httpx.HTTPTransport):
            def handle_request(self, request: httpx.Request) -> httpx.Response:
                request.url = request.url.copy_with(scheme=target.scheme, host=target.host, port=target.port)
                return super().handle_request(request)

        set_client_factory(lambda: httpx.Client(transport=ToFakeHub(), follow_redirects=True, timeout=None))
        close_session()

    def files(self, repo_id: str, revision: str = "main") -> dict[str, bytes]:
        """The files at a branch ("main"), a tag or a commit sha."""
        repo = self.repos[repo_id]
        if revision == "main":
            return repo["main"]
        if revision in repo["tags"]:
            return repo["tags"][revision]
        return repo["commits"][revision]

    def _handler(self):
        hub = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *args) -> None:  # keep test output clean
                pass

            def _send(self, status: int, body: bytes = b"", headers: dict | None = None, head: bool = False):
                self.send_response(status)
                for key, value in (headers or {}).items():
                    self.send_header(key, value)
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                if not head:
                    self.wfile.write(body)

            def _json(self, status: int, payload, headers: dict | None = None):
                headers = {"Content-Type": "application/json", **(headers or {})}
                self._send(status, json.dumps(payload).encode(), headers)

            def _not_found(self, code: str = "EntryNotFound", message: str = "not found", head: bool = False):
                body = json.dumps({"error": message}).encode()
                self._send(404, body, {"X-Error-Code": code, "X-Error-Message": message}, head=head)

            def _body(self) -> bytes:
                return self.rfile.read(int(self.headers.get("Content-Length", 0)))

            def _route(self, method: str) -> None:
                path = unquote(urlparse(self.path).path)
                hub.requests.append(f"{method} {path}")
                for pattern, handler in routes:
                    match = re.fullmatch(pattern, f"{method} {path}")
                    if match:
                        return handler(self, *match.groups())
                self._json(400, {"error": f"fake hub: unsupported {method} {path}"})

            def do_GET(self):
                self._route("GET")

            def do_HEAD(self):
                self._route("HEAD")

            def do_POST(self):
                self._route("POST")

            def do_DELETE(self):
                self._route("DELETE")

            # --- endpoints -------------------------------------------------------------------
            def validate_yaml(self):
                self._body()
                self._json(200, {"errors": [], "warnings": []})

            def create_repo(self):
                payload = json.loads(self._body())
                organization = payload.get("organization")
                repo_id = f"{organization}/{payload['name']}" if organization else payload["name"]
                if repo_id in hub.repos:
                    error = "You already created this dataset repo"
                    return self._json(409, {"error": error, "url": f"{PUBLIC_URL}/datasets/{repo_id}"})
                hub.repos[repo_id] = {"main": {}, "tags": {}, "commits": {}}
                self._json(200, {"url": f"{PUBLIC_URL}/datasets/{repo_id}"})

            def preupload(self, repo_id, revision):
                files = json.loads(self._body())["files"]
                modes = [
                    {"path": f["path"], "uploadMode": "regular", "shouldIgnore": False, "oid": None} for f in files
                ]
                self._json(200, {"files": modes, "commitOid": _sha(hub.repos[repo_id]["main"])})

            def commit(self, repo_id, revision):
                files = hub.repos[repo_id]["main"]
                for line in self._body().decode().splitlines():
                    item = json.loads(line)
                    if item["key"] == "file":
                        files[item["value"]["path"]] = base64.b64decode(item["value"]["content"])
                    elif item["key"] == "deletedFile":
                        files.pop(item["value"]["path"], None)
                oid = _sha(files)
                hub.repos[repo_id]["commits"][oid] = dict(files)
                url = f"{PUBLIC_URL}/datasets/{repo_id}/commit/{oid}"
                self._json(200, {"commitUrl": url, "commitOid": oid, "pullRequestUrl": None})

            def create_tag(self, repo_id, revision):
                tag = json.loads(self._body())["tag"]
                hub.repos[repo_id]["tags"][tag] = dict(hub.repos[repo_id]["main"])
                self._json(200, {})

            def delete_tag(self, repo_id, tag):
                if hub.repos[repo_id]["tags"].pop(tag, None) is None:
                    return self._not_found("RevisionNotFound", "tag not found")
                self._json(200, {})

            def refs(self, repo_id):
                if repo_id not in hub.repos:
                    return self._not_found("RepoNotFound", "repository not found")
                repo = hub.repos[repo_id]
                self._json(
                    200,
                    {
                        "branches": [{"name": "main", "ref": "refs/heads/main", "targetCommit": _sha(repo["main"])}],
                        "tags": [
                            {"name": t, "ref": f"refs/tags/{t}", "targetCommit": _sha(f)}
                            for t, f in repo["tags"].items()
                        ],
                        "converts": [],
                    },
                )

            def info(self, repo_id, revision=None):
                if repo_id not in hub.repos:
                    return self._not_found("RepoNotFound", "repository not found")
                files = hub.files(repo_id, revision or "main")
                self._json(
                    200,
                    {
                        "id": repo_id,
                        "_id": repo_id,
                        "private": False,
                        "sha": _sha(files),
                        "tags": [],
                        "siblings": [{"rfilename": name, "size": len(data)} for name, data in sorted(files.items())],
                    },
                )

            def tree(self, repo_id, revision, prefix=""):
                files = hub.files(repo_id, revision)
                prefix = prefix.strip("/")
                entries = [
                    {"type": "file", "path": n, "size": len(d), "oid": hashlib.sha1(d).hexdigest()}
                    for n, d in sorted(files.items())
                    if not prefix or n.startswith(prefix + "/")
                ]
                self._json(200, entries)

            def resolve(self, repo_id, revision, filename, head=False):
                try:
                    files = hub.files(repo_id, revision)
                except KeyError:
                    return self._not_found("RevisionNotFound", "revision not found", head=head)
                if filename not in files:
                    return self._not_found(head=head)
                data = files[filename]
                headers = {
                    "X-Repo-Commit": _sha(files),
                    "ETag": f'"{hashlib.sha1(data).hexdigest()}"',
                    "Content-Type": "application/octet-stream",
                }
                self._send(200, data, headers, head=head)

        routes = [
            (r"POST /api/repos/create", Handler.create_repo),
            (r"POST /api/validate-yaml", Handler.validate_yaml),
            (r"POST /api/datasets/([^/]+/[^/]+)/preupload/([^/]+)", Handler.preupload),
            (r"POST /api/datasets/([^/]+/[^/]+)/commit/([^/]+)", Handler.commit),
            (r"POST /api/datasets/([^/]+/[^/]+)/tag/([^/]+)", Handler.create_tag),
            (r"DELETE /api/datasets/([^/]+/[^/]+)/tag/([^/]+)", Handler.delete_tag),
            (r"GET /api/datasets/([^/]+/[^/]+)/refs", Handler.refs),
            (r"GET /api/datasets/([^/]+/[^/]+)/revision/([^/]+)", Handler.info),
            (r"GET /api/datasets/([^/]+/[^/]+)", Handler.info),
            (r"GET /api/datasets/([^/]+/[^/]+)/tree/([^/]+)/?(.*)", Handler.tree),
            (r"GET /datasets/([^/]+/[^/]+)/resolve/([^/]+)/(.+)", Handler.resolve),
            (r"HEAD /datasets/([^/]+/[^/]+)/resolve/([^/]+)/(.+)", lambda h, *a: Handler.resolve(h, *a, head=True)),
        ]
        return Handler


def _sha(files: dict[str, bytes]) -> str:
    digest = hashlib.sha1()
    for name in sorted(files):
        digest.update(name.encode() + hashlib.sha1(files[name]).digest())
    return digest.hexdigest()
