"""Role configs, certificates, access control, observability files and systemd units."""

from __future__ import annotations

import ipaddress
import json
import re
import shlex
import stat
from pathlib import Path

import pytest
import yaml
from cryptography import x509
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import NameOID
from gaitflow.stages.graph import load

from gaitflow import deployment
from gaitflow.acl import server_acl
from gaitflow.certs import check_machine, make_bundle
from gaitflow.cli import build_parser, main
from gaitflow.errors import ConfigError

REPO = Path(__file__).resolve().parents[1]
DEPLOY = REPO / "deploy"


# ----------------------------------------------------------------------- role configs


def test_committed_role_configs_are_in_sync_with_the_generator() -> None:
    files = deployment.render()
    assert deployment.stale(DEPLOY, files) == [], "run: gaitflow deploy render"
    assert main(["deploy", "render", "--check"]) == 0


def test_check_detects_a_stale_file(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    assert main(["deploy", "render", "--out", str(tmp_path)]) == 0
    (tmp_path / "roles" / "server.yaml").write_text("role: server\n")
    assert main(["deploy", "render", "--out", str(tmp_path), "--check"]) == 1
    assert "server.yaml" in capsys.readouterr().out


def test_roles_split_the_graph() -> None:
    graph = load()
    topo = deployment.Topology()
    edge = deployment.render_edge(graph, topo, "edge-1")
    server = deployment.render_server(graph, topo)
    aio = deployment.render_all_in_one(graph, topo)
    names = lambda doc: [s["name"] for s in doc["stages"]]  # noqa: E731
    assert names(edge) == ["grab", "calibrate", "clean", "detect", "locate"]
    assert names(server) == ["model", "label", "gait"]
    assert sorted(names(aio)) == sorted(n.name for n in graph.nodes)

    def workers(doc: dict, name: str) -> list[str]:
        return [w["id"] for s in doc["stages"] if s["name"] == name for w in s["workers"]]

    assert {w["camera"] for s in edge["stages"] for w in s["workers"]} == {"cam-1"}
    # The server's per-frame stateful stages run a worker per camera; model one for all.
    assert workers(server, "model") == ["0"]
    assert workers(server, "label") == workers(server, "gait") == ["cam-1", "cam-2"]
    assert workers(aio, "label") == ["0"]
    # Edge -> server: a client with one explicit TLS endpoint, mutual TLS on.
    up = edge["uplink"]
    assert up["bus"]["mode"] == "client" and up["bus"]["connect"] == ["tls/127.0.0.1:7448"]
    assert up["bus"]["tls"]["enable_mtls"] is True
    assert "truth" not in up["streams"] and {"raw", "markers", "calibration"} <= set(up["streams"])
    assert server["router"]["access_control"]["default_permission"] == "deny"
    assert server["cameras"] == ["cam-1", "cam-2"]
    moved = deployment.Topology(locate_on="server")
    assert "locate" in names(deployment.render_server(graph, moved))
    assert {"clean", "blobs"} <= set(
        deployment.render_edge(graph, moved, "edge-1")["uplink"]["streams"]
    )


def test_topology_rejects_bad_values() -> None:
    with pytest.raises(ConfigError):
        deployment.Topology(edges={"edge-1": "cam-1", "edge-2": "cam-1"})
    with pytest.raises(ConfigError):
        deployment.Topology(edges={"Edge 1": "cam-1"})
    with pytest.raises(ConfigError):
        deployment.Topology(locate_on="cloud")


ENDPOINT = re.compile(r"\b(?:tcp|tls|udp|quic)/([^:/\s]+):\d+")


def _strings(doc: object) -> list[str]:
    if isinstance(doc, dict):
        return [s for v in doc.values() for s in _strings(v)]
    if isinstance(doc, list):
        return [s for v in doc for s in _strings(v)]
    return [doc] if isinstance(doc, str) else []


def test_default_configs_stay_on_loopback() -> None:
    for path in sorted((DEPLOY / "roles").glob("*.yaml")):
        doc = yaml.safe_load(path.read_text())
        hosts = [m.group(1) for s in _strings(doc) for m in ENDPOINT.finditer(s)]
        assert hosts, path
        assert set(hosts) == {"127.0.0.1"}, f"{path.name}: {hosts}"
        assert doc["bus"]["multicast_scouting"] is False
        ports = [w["metrics_port"] for s in doc.get("stages", []) for w in s["workers"]]
        assert len(set(ports)) == len(ports), path.name
        assert ports or path.name.endswith(".stages.yaml"), path.name
        watch = doc.get("watch") or {}
        assert watch.get("metrics_host", "127.0.0.1") == "127.0.0.1"
    prom = yaml.safe_load((DEPLOY / "observability" / "prometheus.yml").read_text())
    targets = [t for j in prom["scrape_configs"] for c in j["static_configs"] for t in c["targets"]]
    assert targets and all(t.startswith("127.0.0.1:") for t in targets)


def test_pseudonyms_are_stable_and_do_not_carry_the_id() -> None:
    a = deployment.pseudonym(b"clinic-secret", "Jane Doe 1970-01-01")
    assert a == deployment.pseudonym(b"clinic-secret", "Jane Doe 1970-01-01")
    assert a != deployment.pseudonym(b"other-secret", "Jane Doe 1970-01-01")
    assert re.fullmatch(r"s-[0-9a-f]{10}", a)
    with pytest.raises(ConfigError):
        deployment.pseudonym(b"", "x")


# ----------------------------------------------------------------------- certificates


def test_certs_chain_names_and_key_modes(tmp_path: Path) -> None:
    assert (
        main(
            ["certs", "--out", str(tmp_path), "--machines", "edge-1,server", "--san", "10.200.1.2"]
        )
        == 0
    )
    ca = x509.load_pem_x509_certificate((tmp_path / "ca.pem").read_bytes())
    assert ca.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
    for m in ("edge-1", "server"):
        cert = x509.load_pem_x509_certificate((tmp_path / m / "cert.pem").read_bytes())
        cert.verify_directly_issued_by(ca)
        assert cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value == m
        san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
        assert set(san.get_values_for_type(x509.DNSName)) == {m, "localhost"}
        assert set(san.get_values_for_type(x509.IPAddress)) == {
            ipaddress.ip_address("127.0.0.1"),
            ipaddress.ip_address("10.200.1.2"),
        }
        assert not cert.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
        mode = stat.S_IMODE((tmp_path / m / "key.pem").stat().st_mode)
        assert mode == 0o600
    assert stat.S_IMODE((tmp_path / "ca-key.pem").stat().st_mode) == 0o600
    # A second run adds a machine under the same CA.
    before = (tmp_path / "ca.pem").read_bytes()
    issued = make_bundle(tmp_path, ["edge-2"])
    assert (tmp_path / "ca.pem").read_bytes() == before
    cert = x509.load_pem_x509_certificate(issued["edge-2"].cert.read_bytes())
    cert.verify_directly_issued_by(ca)
    assert isinstance(cert.public_key(), ec.EllipticCurvePublicKey)


def test_cert_machine_names_are_checked() -> None:
    with pytest.raises(ConfigError):
        check_machine("Edge_1")
    with pytest.raises(ConfigError):
        make_bundle("/nonexistent-never-created", [])


# ----------------------------------------------------------------------- access control


def test_acl_edges_publish_only_their_camera() -> None:
    acl = server_acl("clinic", {"edge-1": "cam-1", "edge-2": "cam-2"}, ["grab"])
    rules = {r["id"]: r for r in acl["rules"]}
    assert acl["default_permission"] == "deny"
    pols = {p["subjects"][0]: p for p in acl["policies"] if len(p["subjects"]) == 1}
    for machine, cam in (("edge-1", "cam-1"), ("edge-2", "cam-2")):
        subject = next(s for s in acl["subjects"] if s["id"] == machine)
        assert subject["cert_common_names"] == [machine]
        assert subject["link_protocols"] == ["tls"]
        puts = [r for rid in pols[machine]["rules"] for r in [rules[rid]] if "put" in r["messages"]]
        assert len(puts) == 1
        assert puts[0]["key_exprs"] == [f"gaitflow/clinic/{cam}/**"]
        assert puts[0]["flows"] == ["ingress"]
        # Nothing of the data is ever sent to an edge.
        for rid in pols[machine]["rules"]:
            r = rules[rid]
            if "egress" in r["flows"]:
                assert "put" not in r["messages"], rid


# ----------------------------------------------------------------------- observability


def _exported_metric_names() -> set[str]:
    names: set[str] = set()
    for src in (
        REPO / "stages" / "runtime.py",
        REPO / "stages" / "launcher.py",
        REPO / "gaitflow" / "edgebuffer.py",
    ):
        text = src.read_text()
        for kind, name in re.findall(
            r"\b(Counter|Gauge|Histogram)\(\s*\"(gaitflow_[a-z_]+)\"", text
        ):
            if kind == "Counter":
                names.add(name + "_total")
            elif kind == "Histogram":
                names |= {name + "_bucket", name + "_sum", name + "_count"}
            else:
                names.add(name)
    return names


def test_dashboard_and_alerts_use_exported_metrics() -> None:
    exported = _exported_metric_names()
    assert "gaitflow_stage_processing_seconds_bucket" in exported
    dash = json.loads((DEPLOY / "observability" / "grafana-dashboard.json").read_text())
    exprs = [t["expr"] for p in dash["panels"] for t in p["targets"]]
    alerts = yaml.safe_load((DEPLOY / "observability" / "alerts.yml").read_text())
    rules = {r["alert"]: r for g in alerts["groups"] for r in g["rules"]}
    used = set()
    for e in [*exprs, *(r["expr"] for r in rules.values())]:
        used |= set(re.findall(r"\bgaitflow_[a-z_]+", e))
    assert used and used <= exported, sorted(used - exported)
    kinds = {p["type"] for p in dash["panels"]}
    assert "heatmap" in kinds
    titles = " ".join(p["title"].lower() for p in dash["panels"])
    for word in ("p99", "over budget", "drops", "restarts", "end-to-end", "up"):
        assert word in titles, word
    p99 = rules["GaitflowStageP99OverBudget"]
    assert p99["for"] == "1m" and "0.99" in p99["expr"] and "0.033" in p99["expr"]
    assert "gaitflow_stage_up == 0" in rules["GaitflowStageDown"]["expr"]


def test_systemd_units_run_existing_commands_and_role_files() -> None:
    units = sorted((DEPLOY / "systemd").glob("*.service"))
    assert {u.stem for u in units} >= {"gaitflow-router", "gaitflow-stages", "gaitflow-uplink"}
    subst = {
        "${GAITFLOW_MACHINE}": "server",
        "${GAITFLOW_RECORD_STREAMS}": "raw gait",
    }
    parser = build_parser()
    for u in units:
        text = u.read_text().replace("\\\n", " ")
        assert "[Install]" in text, u.name
        assert "/etc/gaitflow/roles/${GAITFLOW_MACHINE}" in text, u.name
        (line,) = [ln for ln in text.splitlines() if ln.startswith("ExecStart=")]
        cmd = re.search(r"bin/gaitflow (.*?)(?:'|$)", line).group(1)
        cmd = re.sub(r"\$\(date [^)]*\)", "x", cmd)
        for k, v in subst.items():
            cmd = cmd.replace(k, v)
        args = parser.parse_args(shlex.split(cmd))  # exits (fails) on an unknown option
        assert args.func is not None, u.name
        role_files = re.findall(r"/etc/gaitflow/roles/(\S+)", cmd)
        for f in role_files:
            assert (DEPLOY / "roles" / f).exists(), f"{u.name}: {f}"


def test_stage_configs_load_as_the_runtime_reads_them() -> None:
    from gaitflow.stages.runtime import RuntimeOptions, StageConfig

    for path in sorted((DEPLOY / "roles").glob("*.stages.yaml")):
        cfg = StageConfig.load(str(path))
        opt = RuntimeOptions.from_mapping(cfg.runtime, str(path))
        assert opt.metrics_host == "127.0.0.1"
        assert opt.reorder_timeout_s == deployment.REORDER_TIMEOUT_S
        assert cfg.bus.connect == ("tcp/127.0.0.1:7447",)
        assert dict(cfg.bus.extra)["connect/retry"] == deployment.RECONNECT
        cfg.bus.to_zenoh()  # every key is one zenoh 1.x accepts
    role = deployment.load_role(DEPLOY / "roles" / "server.yaml")
    from gaitflow.edgebuffer import router_config

    rcfg, listen = router_config(role)
    assert listen == ("tcp/127.0.0.1:7447", "tls/127.0.0.1:7448")
    rcfg.to_zenoh()  # the access-control section and TLS keys are valid zenoh config


def test_run_role_file_starts_exactly_the_role_workers(tmp_path: Path) -> None:
    """`gaitflow run --role-file` plans one process per listed worker, with its port."""
    from gaitflow.stages.launcher import Launcher

    role = deployment.load_role(DEPLOY / "roles" / "server.yaml")
    plan = deployment.role_plan(role)
    la = Launcher(load(), endpoint="tcp/127.0.0.1:7447", router=False, plan=plan)
    got = {(c.name, c.worker): c.argv for c in la.children}
    assert sorted(got) == [
        ("gait", "cam-1"), ("gait", "cam-2"), ("label", "cam-1"), ("label", "cam-2"),
        ("model", "0"),
    ]  # fmt: skip
    argv = got[("label", "cam-2")]
    assert argv[argv.index("--camera") + 1] == "cam-2"
    port = argv[argv.index("--metrics-port") + 1]
    listed = [w for s in role["stages"] for w in s["workers"] if s["name"] == "label"]
    assert int(port) == next(w["metrics_port"] for w in listed if w["camera"] == "cam-2")
    assert "--camera" not in got[("model", "0")]
    # Without a role file, --cameras gives the same per-camera split.
    la2 = Launcher(load(), role="server", router=False, cameras=["cam-1", "cam-2"])
    assert sorted((c.name, c.worker) for c in la2.children) == sorted(got)
