"""deploy/'s topology on loopback, without Docker: Redis, the service replicas and nginx, wired as
`docker-compose.yml` and `nginx.conf` say.

    python -m deploy.local                   # (from the repository root) a small synthetic model + library, then
                                             # everything up; Ctrl-C stops it
    python -m deploy.local --assets DIR      # serve DIR instead (model.onnx, library/: see deploy/assets/README.md)

Everything comes from the deploy files: each replica's environment (the Dockerfile's ENV under the compose
service's `environment`) and command (its `command`, else the Dockerfile's CMD), Redis's command, nginx.conf whole,
and the start order and health gates of `depends_on`. Two kinds of thing are rewritten, nothing else:

- addresses: `<compose service>:<container port>` → 127.0.0.1:<free port> (nginx upstreams, HAPTICLINK_REDIS_URL),
  the replicas' HAPTICLINK_HOST/HAPTICLINK_PORT, nginx's `listen <container port>`;
- file-system paths: a volume's container path → the host folder it mounts (the replicas' model, library and
  fleet API key file), nginx's logs, pid and temp folders → a work folder (`-p`/`-c`/`-g`, so nginx runs as any user).

A broken pinning map, upstream, header, timeout or HAPTICLINK_* value is therefore broken here too.
Opening a session needs a fleet API key: the replicas read theirs from HAPTICLINK_API_KEYS_FILE (compose puts it
in the assets folder); `Topology` uses the file's first key, or writes a new key there when there is no file, and
hands it to robots in `robot_options`. `/metrics` needs the metrics token compose passes on from the shell
(HAPTICLINK_METRICS_TOKEN): `Topology` uses the shell's, or sets a new one as that shell variable would, and
keeps it as `metrics_token` for scrapers. `Topology` is what tests/deploy/test_topology.py drives; the process that
starts it must outlive it.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import re
import secrets
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import urlsplit, urlunsplit

import httpx

from service.fleet import parse_keys
from service.launcher import free_port, wait_until_ready
from service.settings import ENV_PREFIX, env_name

DEPLOY_DIR = Path(__file__).resolve().parent
REPO_DIR = DEPLOY_DIR.parent  # replicas run this checkout's code (`python -m` puts the working folder first)
LOOPBACK = "127.0.0.1"
#: pyproject's [project.scripts], as `python -m` modules: the image's CMD runs them by these names
CONSOLE_SCRIPTS = {"hapticlink": "service.cli"}
NGINX_TEMP_PATHS = (
    "client_body_temp_path",
    "proxy_temp_path",
    "fastcgi_temp_path",
    "uwsgi_temp_path",
    "scgi_temp_path",
)
#: the model kind of the synthetic serving assets: tactile only, so the replicas embed no frame and start light
SYNTHETIC_MODEL = "ridge-tactile"
START_TIMEOUT_S = 120.0  # a replica loads and warms its model on a busy 2-core machine


class TopologyError(RuntimeError):
    """A part of the topology could not start or answer; the message names it and where its log is."""


def find_program(name: str) -> str | None:
    """`name` on PATH or in the sbin folders (nginx lives in /usr/sbin, often off a user's PATH)."""
    return shutil.which(name) or shutil.which(name, path="/usr/local/sbin:/usr/sbin:/sbin")


# ---- reading the deploy files ----------------------------------------------------------------------
_COMPOSE_VAR = re.compile(r"\$\{(\w+)(?::?-([^}]*))?\}")


def substitute(text: str, env: Mapping[str, str]) -> str:
    """Compose's `${VAR}` / `${VAR:-default}` interpolation."""
    return _COMPOSE_VAR.sub(lambda m: env.get(m.group(1)) or (m.group(2) or ""), text)


def _instructions(dockerfile: str) -> list[tuple[str, str]]:
    """(INSTRUCTION, rest) of the final build stage, continuation lines joined, comments dropped."""
    joined = re.sub(
        r"\\\n", " ", "\n".join(line for line in dockerfile.splitlines() if not line.lstrip().startswith("#"))
    )
    out: list[tuple[str, str]] = []
    for line in joined.splitlines():
        if not line.strip():
            continue
        word, _, rest = line.strip().partition(" ")
        if word.upper() == "FROM":
            out = []  # a new stage: what the image runs with is the last stage's
        out.append((word.upper(), rest.strip()))
    return out


def dockerfile_env(dockerfile: str) -> dict[str, str]:
    """The ENV of the image's final stage (`ENV K=V …` and the legacy `ENV K V`)."""
    env: dict[str, str] = {}
    for word, rest in _instructions(dockerfile):
        if word != "ENV":
            continue
        tokens = shlex.split(rest)
        if tokens and "=" not in tokens[0]:
            env[tokens[0]] = " ".join(tokens[1:])
        else:
            env.update(token.split("=", 1) for token in tokens)
    return env


def dockerfile_cmd(dockerfile: str) -> list[str]:
    """The final stage's CMD, exec (JSON) or shell form."""
    cmds = [rest for word, rest in _instructions(dockerfile) if word == "CMD"]
    if not cmds:
        raise ValueError("the Dockerfile has no CMD")
    return json.loads(cmds[-1]) if cmds[-1].startswith("[") else ["/bin/sh", "-c", cmds[-1]]


def _environment(service: dict) -> dict[str, str]:
    env = service.get("environment") or {}
    if isinstance(env, list):
        env = dict(item.split("=", 1) for item in env)
    return {str(k): "" if v is None else str(v) for k, v in env.items()}


def _seconds(value: str | int | float, default: float) -> float:
    """A compose duration ("10s", "1m30s", 5) in seconds."""
    if value is None:
        return default
    if isinstance(value, (int, float)):
        return float(value)
    units = {"h": 3600.0, "m": 60.0, "s": 1.0, "ms": 1e-3}
    parts = re.findall(r"(\d+(?:\.\d+)?)(ms|h|m|s)", value)
    if not parts:
        raise ValueError(f"not a compose duration: {value!r}")
    return sum(float(n) * units[u] for n, u in parts)


@dataclass(frozen=True)
class DeployFiles:
    """docker-compose.yml (parsed), nginx.conf and the Dockerfile, as the deploy folder holds them."""

    compose: dict
    nginx_conf: str
    dockerfile: str
    folder: Path

    @classmethod
    def read(cls, folder: Path = DEPLOY_DIR) -> DeployFiles:
        import yaml  # the dev extra; the serving image does not need this module

        compose = yaml.safe_load((folder / "docker-compose.yml").read_text())
        return cls(compose, (folder / "nginx.conf").read_text(), (folder / "Dockerfile").read_text(), folder)

    @property
    def services(self) -> dict[str, dict]:
        return self.compose["services"]

    def replicas(self) -> list[str]:
        """Services built from the service's Dockerfile."""
        return [name for name, svc in self.services.items() if "build" in svc]

    def _by_image(self, image: str) -> str:
        names = [name for name, svc in self.services.items() if svc.get("image", "").split(":")[0].endswith(image)]
        if len(names) != 1:
            raise ValueError(f"docker-compose.yml must run exactly one {image} service, found {names}")
        return names[0]

    def redis(self) -> str:
        return self._by_image("redis")

    def load_balancer(self) -> str:
        return self._by_image("nginx")

    def start_order(self) -> list[str]:
        """Services ordered so that each comes after what it depends_on (compose's order)."""
        order: list[str] = []

        def visit(name: str, path: tuple[str, ...]) -> None:
            if name in order:
                return
            if name in path:
                raise ValueError(f"depends_on cycle: {' → '.join(path + (name,))}")
            for dep in self.depends_on(name):
                visit(dep, path + (name,))
            order.append(name)

        for name in self.services:
            visit(name, ())
        return order

    def depends_on(self, name: str) -> dict[str, str]:
        """{dependency: condition} (a plain list means service_started)."""
        deps = self.services[name].get("depends_on") or {}
        if isinstance(deps, list):
            return {d: "service_started" for d in deps}
        return {d: (spec or {}).get("condition", "service_started") for d, spec in deps.items()}

    def command(self, name: str) -> list[str]:
        """The service's command: compose `command`, else (replicas) the image's CMD."""
        cmd = self.services[name].get("command")
        if cmd is None:
            if name not in self.replicas():
                raise ValueError(f"service {name} has no command")
            return dockerfile_cmd(self.dockerfile)
        return shlex.split(cmd) if isinstance(cmd, str) else [str(c) for c in cmd]

    def environment(self, name: str, host_env: Mapping[str, str]) -> dict[str, str]:
        """What the container sees: the image's ENV (replicas), then compose's `environment`, interpolated."""
        base = dockerfile_env(self.dockerfile) if name in self.replicas() else {}
        return {**base, **{k: substitute(v, host_env) for k, v in _environment(self.services[name]).items()}}

    def mounts(self, name: str, host_env: Mapping[str, str]) -> dict[str, Path]:
        """{container path: host path} of the service's bind mounts (short syntax), relative to the compose file."""
        out = {}
        for volume in self.services[name].get("volumes") or []:
            source, target = substitute(str(volume), host_env).split(":")[:2]
            out[target.rstrip("/")] = (self.folder / source).resolve()
        return out

    def published_port(self, name: str) -> tuple[int, int]:
        """(host port, container port) of the service's one published port."""
        ports = self.services[name].get("ports") or []
        if len(ports) != 1:
            raise ValueError(f"service {name} must publish exactly one port, got {ports}")
        host, _, container = str(ports[0]).rpartition(":")
        return int(host.rpartition(":")[2]), int(container)

    def health_url(self, name: str) -> str | None:
        """The URL the service's healthcheck fetches, if it fetches one."""
        test = " ".join(str(t) for t in (self.services[name].get("healthcheck") or {}).get("test", []))
        found = re.search(r"https?://[^\s'\"]+", test)
        return found.group(0) if found else None

    def stop_grace_s(self, name: str) -> float:
        return _seconds(self.services[name].get("stop_grace_period"), 10.0)


# ---- rewriting addresses and paths ------------------------------------------------------------------
def rewrite_addresses(text: str, ports: Mapping[str, int]) -> str:
    """Every `<service>:<port>` of a compose service in `ports` → 127.0.0.1:<its loopback port>."""
    if not ports:
        return text
    names = "|".join(re.escape(n) for n in sorted(ports, key=len, reverse=True))
    return re.sub(rf"(?<![\w.-])({names}):\d+\b", lambda m: f"{LOOPBACK}:{ports[m.group(1)]}", text)


def rewrite_mounts(value: str, mounts: Mapping[str, Path]) -> str:
    """A path inside a mounted container folder → the same path in the host folder it mounts."""
    for target, source in mounts.items():
        if value == target or value.startswith(target + "/"):
            return str(source) + value[len(target) :]
    return value


def replica_environment(
    files: DeployFiles, name: str, port: int, ports: Mapping[str, int], host_env: Mapping[str, str]
) -> dict[str, str]:
    """The replica's container environment with addresses and mounted paths made local (and nothing else)."""
    mounts = files.mounts(name, host_env)
    env = {k: rewrite_mounts(rewrite_addresses(v, ports), mounts) for k, v in files.environment(name, host_env).items()}
    env[env_name("host")] = LOOPBACK  # the container's 0.0.0.0: every interface of its own network namespace
    env[env_name("port")] = str(port)
    return env


def nginx_config(conf: str, ports: Mapping[str, int], container_port: int, listen_port: int, workdir: Path) -> str:
    """nginx.conf with the upstream addresses, the listen address and the log and temp paths made local."""
    out = rewrite_addresses(conf, ports)
    out, n = re.subn(rf"(\blisten\s+){container_port}\b", rf"\g<1>{LOOPBACK}:{listen_port}", out)
    if n != 1:
        raise ValueError(f"nginx.conf must have one `listen {container_port}` (compose publishes that port), found {n}")
    logs = workdir / "logs"
    out = re.sub(
        r"(\b(?:access|error)_log\s+)(/\S+?)(?=[\s;])", lambda m: f"{m.group(1)}{logs / Path(m.group(2)).name}", out
    )
    temp = "".join(f"    {d} {workdir / 'tmp' / d.split('_temp')[0]};\n" for d in NGINX_TEMP_PATHS)
    out, n = re.subn(r"^(http\s*\{[^\n]*\n)", lambda m: m.group(1) + temp, out, count=1, flags=re.M)
    if n != 1:
        raise ValueError("nginx.conf has no `http {` block")
    return out


def nginx_command(program: str, conf: str, workdir: Path) -> list[str]:
    """argv running nginx in the foreground on `conf` (nginx_config's output, written to workdir/nginx.conf), its
    pid, error log and temp folders in `workdir` (created here)."""
    logs = workdir / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    (workdir / "tmp").mkdir(exist_ok=True)
    conf_path = workdir / "nginx.conf"
    conf_path.write_text(conf)
    main = ["daemon off;", f"pid {workdir / 'nginx.pid'};", f"error_log {logs / 'error.log'} notice;"]
    if os.geteuid() == 0 and not re.search(r"^\s*user\s", conf, re.M):
        main.append("user root;")  # as root, workers would switch to `nobody`, who cannot enter a private tmp folder
    return [program, "-e", str(logs / "error.log"), "-p", str(workdir), "-c", str(conf_path), "-g", " ".join(main)]


# ---- processes ---------------------------------------------------------------------------------------
@dataclass
class Service:
    """One running service of the topology: its process, loopback port and log file."""

    name: str
    port: int
    log_path: Path
    argv: list[str]
    env: dict[str, str] = field(default_factory=dict)
    proc: subprocess.Popen | None = None

    @property
    def url(self) -> str:
        return f"http://{LOOPBACK}:{self.port}"

    @property
    def ws_url(self) -> str:
        return f"ws://{LOOPBACK}:{self.port}"

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def log_tail(self, lines: int = 30) -> str:
        try:
            return "\n".join(self.log_path.read_text(errors="replace").splitlines()[-lines:])
        except OSError:
            return ""


class Topology:
    """Redis, the replicas and nginx from `files` on loopback (`with Topology(assets) as topo:`).

    assets: the folder compose mounts at the replicas' /srv/hapticlink (model.onnx, library/, …).
    lb_port: nginx's loopback port (0: a free one). workdir: logs, configs and nginx's folders (default: a
    new temporary folder, removed by stop() unless keep_workdir). api_key: the fleet key robots open sessions
    with (default: the first key of the replicas' key file, or a new one written there; see `fleet_key`).
    metrics_token: what scrapes the replicas' /metrics (the shell's HAPTICLINK_METRICS_TOKEN, else a new one).
    After start(): `url` is nginx's, `replicas` maps instance id → Service (each reachable directly, as an
    operator inside the network would), `redis_url`, `api_key`, and `robot_options` the keyword arguments a
    RobotClient needs besides url and source (the API key).
    """

    def __init__(
        self,
        assets: Path,
        *,
        files: DeployFiles | None = None,
        lb_port: int = 0,
        workdir: Path | None = None,
        keep_workdir: bool = False,
        start_timeout_s: float = START_TIMEOUT_S,
        api_key: str | None = None,
    ) -> None:
        self.files = files or DeployFiles.read()
        self.assets = Path(assets).resolve()
        self._own_workdir = workdir is None
        self.workdir = Path(workdir) if workdir is not None else Path(tempfile.mkdtemp(prefix="hapticlink-topology-"))
        self.keep_workdir = keep_workdir
        self.start_timeout_s = start_timeout_s
        # What `docker compose` would interpolate with: this shell's variables, the assets folder as HAPTICLINK_ASSETS.
        self.host_env = {**os.environ, "HAPTICLINK_ASSETS": str(self.assets)}
        self.redis_name = self.files.redis()
        self.lb_name = self.files.load_balancer()
        self.replica_names = self.files.replicas()
        self.ports = {name: free_port() for name in self.files.services}
        if lb_port:
            self.ports[self.lb_name] = lb_port
        self.services: dict[str, Service] = {}
        self.replicas: dict[str, Service] = {}  # instance id → service
        self.api_key = api_key
        # The scraper's token of the replicas' /metrics: this shell's HAPTICLINK_METRICS_TOKEN, which compose hands
        # them, else one made for this run (no token would close /metrics).
        self.metrics_token = self.host_env.get(env_name("metrics_token")) or secrets.token_urlsafe(24)
        self.host_env[env_name("metrics_token")] = self.metrics_token
        # What every robot must present to open a session: the fleet API key (set by start()).
        self.robot_options: dict[str, object] = {}

    # -- what runs ------------------------------------------------------------------------------------
    @property
    def url(self) -> str:
        return self.services[self.lb_name].url

    @property
    def redis_url(self) -> str:
        return f"redis://{LOOPBACK}:{self.ports[self.redis_name]}/0"

    def instance_of(self, name: str) -> str:
        return self.files.environment(name, self.host_env)[env_name("instance_id")]

    def key_files(self) -> list[Path]:
        """The fleet API key files the replicas read (their HAPTICLINK_API_KEYS_FILE, mounted paths made local)."""
        found: list[Path] = []
        for name in self.replica_names:
            value = self.files.environment(name, self.host_env).get(env_name("api_keys_file"))
            if value:
                path = Path(rewrite_mounts(value, self.files.mounts(name, self.host_env)))
                if path not in found:
                    found.append(path)
        return found

    def fleet_key(self) -> str:
        """The key robots open sessions with: `api_key`, else the first key the replicas accept (their key file,
        then HAPTICLINK_API_KEYS), else a new one appended to their key file (created 0600 if missing). A given
        `api_key` is written only into a file that holds no key yet: a user's key file is never edited."""
        files = self.key_files()
        static = [
            key
            for name in self.replica_names
            for key in parse_keys(self.files.environment(name, self.host_env).get(env_name("api_keys"), ""), ",")
        ]
        if not files and not static:
            raise TopologyError(
                "docker-compose.yml gives the replicas no fleet API key (neither HAPTICLINK_API_KEYS_FILE "
                "nor HAPTICLINK_API_KEYS): no robot could open a session"
            )
        in_files = [
            key for path in files if path.is_file() for key in parse_keys(path.read_text(encoding="utf-8"), "\n")
        ]
        known = in_files + static
        key = self.api_key or (known[0] if known else secrets.token_urlsafe(24))
        if key in known:
            return key
        if known or not files:
            raise TopologyError(
                "the given api_key is not one the replicas accept: add it to "
                f"{', '.join(map(str, files)) or 'HAPTICLINK_API_KEYS'}, or leave api_key out to use theirs"
            )
        for path in files:  # none holds a key yet
            path.parent.mkdir(parents=True, exist_ok=True)
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o600)
            with os.fdopen(fd, "a", encoding="utf-8") as out:
                out.write(f"# fleet API key written by deploy/local.py\n{key}\n")
        return key

    def _plan(self, name: str) -> Service:
        log_path = self.workdir / "logs" / f"{name}.log"
        port = self.ports[name]
        if name == self.redis_name:
            argv = self.files.command(name)
            program = find_program(argv[0])
            if program is None:
                raise TopologyError(f"{argv[0]} is not installed (apt-get install redis-server)")
            return Service(
                name,
                port,
                log_path,
                [program, *argv[1:], "--bind", LOOPBACK, "--port", str(port), "--dir", str(self.workdir)],
            )
        if name == self.lb_name:
            program = find_program("nginx")
            if program is None:
                raise TopologyError("nginx is not installed (apt-get install nginx)")
            _, container_port = self.files.published_port(name)
            upstreams = {n: self.ports[n] for n in self.files.services if n != name}
            conf = nginx_config(self.files.nginx_conf, upstreams, container_port, port, self.workdir)
            return Service(name, port, log_path, nginx_command(program, conf, self.workdir))
        if name in self.replica_names:
            argv = self.files.command(name)
            if argv[0] in CONSOLE_SCRIPTS:
                argv = [sys.executable, "-m", CONSOLE_SCRIPTS[argv[0]], *argv[1:]]
            others = {n: p for n, p in self.ports.items() if n != name}
            env = replica_environment(self.files, name, port, others, self.host_env)
            return Service(name, port, log_path, argv, env)
        raise TopologyError(f"don't know how to run compose service {name!r} without Docker")

    def start(self) -> Topology:
        (self.workdir / "logs").mkdir(parents=True, exist_ok=True)
        (self.workdir / "tmp").mkdir(exist_ok=True)
        self.api_key = self.fleet_key()
        self.robot_options = {"api_key": self.api_key}
        try:
            for name in self.files.start_order():
                for dep, condition in self.files.depends_on(name).items():
                    if condition == "service_healthy":
                        self.wait_healthy(dep)
                self._start(self._plan(name))
            for name in self.services:
                self.wait_healthy(name)
            for replica in self.replicas.values():
                self.wait_ready(replica)
        except BaseException:
            self.stop()
            raise
        return self

    def _start(self, service: Service) -> None:
        # The replicas get the container's environment, not this shell's HAPTICLINK_* settings.
        env = {k: v for k, v in os.environ.items() if not k.startswith(ENV_PREFIX)}
        env.update(service.env)
        with open(service.log_path, "ab") as log:
            service.proc = subprocess.Popen(
                service.argv,
                env=env,
                stdin=subprocess.DEVNULL,
                stdout=log,
                stderr=subprocess.STDOUT,
                cwd=REPO_DIR if service.name in self.replica_names else self.workdir,
                start_new_session=True,
            )
        self.services[service.name] = service
        if service.name in self.replica_names:
            self.replicas[self.instance_of(service.name)] = service

    def _check_running(self, service: Service) -> None:
        if not service.alive():
            code = service.proc.returncode if service.proc else None
            raise TopologyError(
                f"{service.name} exited (code {code}); its log {service.log_path} ends:\n{service.log_tail()}"
            )

    def healthy(self, name: str) -> bool:
        """The service's compose healthcheck, made local: Redis answers PING; an HTTP check's URL answers 2xx."""
        service = self.services[name]
        if name == self.redis_name:
            import redis

            with (
                contextlib.suppress(redis.RedisError),
                redis.Redis(host=LOOPBACK, port=service.port, socket_timeout=2) as r,
            ):
                return bool(r.ping())
            return False
        url = self.files.health_url(name)
        if url is None:
            return True
        parts = urlsplit(url)  # the check runs inside the container: its own address is our service's port
        local = urlunsplit((parts.scheme, f"{LOOPBACK}:{service.port}", parts.path, parts.query, ""))
        with contextlib.suppress(httpx.HTTPError):
            return httpx.get(local, timeout=2).is_success
        return False

    def wait_healthy(self, name: str) -> None:
        service = self.services[name]
        deadline = time.monotonic() + self.start_timeout_s
        while not self.healthy(name):
            self._check_running(service)
            if time.monotonic() > deadline:
                raise TopologyError(
                    f"{name} did not become healthy in {self.start_timeout_s:g} s; log:\n{service.log_tail()}"
                )
            time.sleep(0.1)

    def wait_ready(self, replica: Service) -> None:
        """Until GET /ready answers 200 (model and library loaded and warmed up)."""
        try:
            wait_until_ready(
                f"{replica.url}/ready", timeout_s=self.start_timeout_s, alive=replica.alive, describe=replica.log_tail
            )
        except RuntimeError as exc:
            raise TopologyError(f"{replica.name}: {exc}") from None

    def kill(self, name: str, sig: int = signal.SIGKILL) -> None:
        """Send `sig` to a service's process (SIGKILL: it dies at once, as a crashed container does)."""
        service = self.services[name]
        if service.alive():
            service.proc.send_signal(sig)
            if sig == signal.SIGKILL:
                service.proc.wait()

    def stop(self) -> None:
        """Stop every service, dependents first (SIGTERM, then SIGKILL after compose's stop_grace_period)."""
        for name in reversed([n for n in self.files.start_order() if n in self.services]):
            service = self.services[name]
            if service.proc is None:
                continue
            if service.alive():
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(service.proc.pid, signal.SIGTERM)
                try:
                    service.proc.wait(timeout=self.files.stop_grace_s(name))
                except subprocess.TimeoutExpired:
                    pass
            with contextlib.suppress(ProcessLookupError):
                os.killpg(service.proc.pid, signal.SIGKILL)  # whatever is left of its group (nginx workers)
            with contextlib.suppress(subprocess.TimeoutExpired):
                service.proc.wait(timeout=5)
        if self._own_workdir and not self.keep_workdir:
            shutil.rmtree(self.workdir, ignore_errors=True)

    def __enter__(self) -> Topology:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def describe(self) -> str:
        lines = [f"nginx       {self.url}   (compose publishes it as {self.files.published_port(self.lb_name)[0]})"]
        for instance, service in self.replicas.items():
            lines.append(f"{instance:<11} {service.url}   ({service.name})")
        lines.append(f"redis       {self.redis_url}")
        lines.append(f"logs        {self.workdir / 'logs'}")
        return "\n".join(lines)


# ---- assets --------------------------------------------------------------------------------------------
def synthetic_assets(root: Path, n_textures: int = 12) -> Path:
    """A serving-assets folder (model.onnx, library/, as deploy/assets/README.md lays it out) holding a synthetic
    library and the demo's tactile-only model kind (ridge-tactile) trained on a synthetic dataset, built once
    under root/build. Tactile only (no backbone, no frames to embed): small to build and light to serve."""
    from models.offline.datasets.build import build
    from models.offline.train import train_and_export
    from texture_library.synthetic_library import build_synthetic_library

    library, model = root / "build" / "library", root / "build" / f"{SYNTHETIC_MODEL}.onnx"
    if not (library / "library.json").is_file():
        build_synthetic_library(library, n_textures=n_textures, image_size=256)
    if not model.is_file():
        dataset = build("synthetic", root / "build" / "dataset", n_textures=n_textures, duration_s=6, image_size=256)
        train_and_export(dataset, SYNTHETIC_MODEL, model)
    assets = root / "assets"
    assets.mkdir(parents=True, exist_ok=True)
    for link, target in ((assets / "model.onnx", model), (assets / "library", library)):
        if not link.exists():
            link.symlink_to(target.resolve())
    return assets


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m deploy.local", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument(
        "--assets", type=Path, help="serving assets folder (default: a synthetic model and library, built once)"
    )
    p.add_argument(
        "--build-dir",
        type=Path,
        default=Path(tempfile.gettempdir()) / "hapticlink-topology-assets",
        help="where the synthetic assets are built and cached",
    )
    p.add_argument("--port", type=int, default=None, help="nginx's port (default: the one compose publishes)")
    p.add_argument("--workdir", type=Path, help="logs and configs (default: a temporary folder, kept while running)")
    args = p.parse_args(argv)
    assets = args.assets or synthetic_assets(args.build_dir)
    files = DeployFiles.read()
    port = args.port if args.port is not None else files.published_port(files.load_balancer())[0]
    topology = Topology(assets, files=files, lb_port=port, workdir=args.workdir)
    print("starting redis, the replicas and nginx …", flush=True)
    try:
        topology.start()
    except TopologyError as exc:
        print(f"python -m deploy.local: error: {exc}", file=sys.stderr)
        return 1
    print(topology.describe())
    keys = topology.key_files()
    key = f"HAPTICLINK_API_KEY=$(grep -v '^#' {keys[0]} | head -1) " if keys else "HAPTICLINK_API_KEY=<a fleet key> "
    print(
        f"\ntry:  {key}hapticlink robot --url {topology.url} --source simulated:{assets / 'library'}:<entry id>\n"
        "Ctrl-C stops.",
        flush=True,
    )
    try:
        while all(s.alive() for s in topology.services.values()):
            time.sleep(0.5)
        gone = [s.name for s in topology.services.values() if not s.alive()]
        print(f"stopped: {', '.join(gone)} exited", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 0
    finally:
        topology.stop()


if __name__ == "__main__":
    sys.exit(main())
