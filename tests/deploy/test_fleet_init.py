"""`semfleet fleet init` (issue 13, item 1) and the JSON5/TOML merge rule of the Zenoh settings
(item 3): the files a secure fleet needs, loadable as they are; secrets private; a conflict
between a JSON5 file and the config's fields is an error naming both, never a silent override.
Real connections over these files: tests/deploy/test_fleet_secure.py."""

from __future__ import annotations

import base64
import json
import shutil
import stat
import tomllib
from pathlib import Path

import json5
import pytest
import tomli_w
from cryptography import x509
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric import ec, ed25519
from cryptography.x509.oid import NameOID

from agents.transport.zenoh_transport import ZenohConfigError, ZenohSettings
from deploy.cli.main import main
from deploy.operator.agent_config import AgentConfigError, load_agent_config
from sim.loader import load_scenario
from sim.robot_model import dump_robot_model

ROBOTS = ("r1", "r2", "r3")


@pytest.fixture(scope="module")
def fleet(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("fleet") / "lab"
    args = ["fleet", "init", "--fleet", "lab", "--robots", ",".join(ROBOTS), "--operator", "ops",
            "--scenario", "paper", "--base-port", "17600", "-o", str(out)]  # fmt: skip
    code = main(args)
    assert code == 0
    return out


def _cert(path: Path) -> x509.Certificate:
    return x509.load_pem_x509_certificate(path.read_bytes())


def test_every_member_has_a_certificate_of_the_fleet_ca_with_its_name(fleet: Path) -> None:
    ca = _cert(fleet / "ca" / "ca.pem")
    ca_key = ca.public_key()
    assert isinstance(ca_key, ec.EllipticCurvePublicKey)
    for name, folder in [*((r, fleet / "robots" / r) for r in ROBOTS), ("ops", fleet / "operator")]:
        cert = _cert(folder / "tls.pem")
        cn = cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value
        assert cn == name
        assert cert.issuer == ca.subject
        cert.verify_directly_issued_by(ca)
        key = serialization.load_pem_private_key((folder / "tls.key").read_bytes(), None)
        assert key.public_key() == cert.public_key()
        assert (folder / "ca.pem").read_bytes() == (fleet / "ca" / "ca.pem").read_bytes()


def test_secrets_are_private_and_the_roster_holds_every_signing_key(fleet: Path) -> None:
    secrets = [fleet / "ca" / "ca.key", *fleet.glob("*/*/tls.key"), *fleet.glob("*/*/signing.key")]
    secrets.append(fleet / "operator" / "tls.key")
    assert len(secrets) == 1 + 2 * len(ROBOTS) + 1
    for path in secrets:
        assert stat.S_IMODE(path.stat().st_mode) == 0o600, path
    roster = tomllib.loads((fleet / "roster.toml").read_text())
    assert roster["fleet"] == "lab" and sorted(roster["robots"]) == list(ROBOTS)
    for r in ROBOTS:
        key = serialization.load_pem_private_key(
            (fleet / "robots" / r / "signing.key").read_bytes(), None
        )
        assert isinstance(key, ed25519.Ed25519PrivateKey)
        public = base64.b64decode(roster["robots"][r]["signing_key"])
        assert public == key.public_key().public_bytes_raw()
        assert (fleet / "robots" / r / "roster.toml").read_text() == (
            fleet / "roster.toml"
        ).read_text()


def test_each_robot_folder_loads_as_an_agent_config_with_mutual_tls(fleet: Path) -> None:
    s = load_scenario("paper")
    for i, r in enumerate(ROBOTS):
        c = load_agent_config(fleet / "robots" / r / "agent.toml", r)
        assert c.fleet == "lab" and c.roster == frozenset(ROBOTS)
        assert c.start == tuple(float(v) for v in s.robot(r).start)
        assert c.model == s.robot_model()
        assert c.zenoh.mutual_tls()
        doc = c.zenoh.document()
        assert doc["listen"]["endpoints"] == [f"tls/127.0.0.1:{17600 + i}"]
        assert doc["connect"]["endpoints"] == [f"tls/127.0.0.1:{17600 + j}" for j in range(i)]
        assert doc["scouting"]["gossip"]["enabled"] is False
        tls = doc["transport"]["link"]["tls"]
        # relative paths of the file are resolved against its folder
        assert tls["listen_private_key"] == str((fleet / "robots" / r / "tls.key").resolve())
        c.zenoh.config()  # Zenoh accepts the merged document


def test_access_control_lets_each_robot_put_only_on_its_own_keys(fleet: Path) -> None:
    doc = json5.loads((fleet / "robots" / "r2" / "zenoh.json5").read_text())
    acl = doc["access_control"]
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    rules = {rule["id"]: rule for rule in acl["rules"]}
    subjects = {sub["id"]: sub for sub in acl["subjects"]}
    allowed: dict[str, set[str]] = {}  # certificate CN → keys it may put on, ingress
    for policy in acl["policies"]:
        for rid in policy["rules"]:
            rule = rules[rid]
            if "put" in rule["messages"] and "ingress" in rule["flows"]:
                for sid in policy["subjects"]:
                    for cn in subjects[sid]["cert_common_names"]:
                        allowed.setdefault(cn, set()).update(rule["key_exprs"])
    p = "semfleet/lab"
    for r in ROBOTS:
        assert allowed[r] == {f"{p}/stack/{r}", f"{p}/stack/{r}/to/*", f"{p}/estimate/{r}",
                              f"{p}/frames/{r}", f"{p}/ctl/need/{r}"}  # fmt: skip
    assert allowed["ops"] == {f"{p}/ctl/**", f"{p}/sim/**"}


def test_fleet_init_refuses_to_overwrite_a_fleet_and_needs_the_model(
    fleet: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    before = (fleet / "ca" / "ca.key").read_bytes()
    assert main(["fleet", "init", "--fleet", "lab", "--robots", "r1", "--scenario", "paper",
                 "-o", str(fleet)]) == 2  # fmt: skip
    assert "not empty" in capsys.readouterr().err
    assert (fleet / "ca" / "ca.key").read_bytes() == before
    assert (
        main(["fleet", "init", "--fleet", "lab", "--robots", "r1", "-o", str(tmp_path / "a")]) == 2
    )
    assert "--model FILE with --start" in capsys.readouterr().err
    assert main(["fleet", "init", "--fleet", "lab", "--robots", "r1,r9", "--scenario", "paper",
                 "-o", str(tmp_path / "b")]) == 2  # fmt: skip
    assert "r9 is not a robot of paper" in capsys.readouterr().err
    model = tmp_path / "model.toml"
    model.write_text((fleet / "robots" / "r1" / "model.toml").read_text())
    args = ["fleet", "init", "--fleet", "lab", "--robots", "a,b", "--model", str(model),
            "--start", "a=0,0,0", "-o", str(tmp_path / "c")]  # fmt: skip
    assert main(args) == 2
    assert "no start pose for b" in capsys.readouterr().err
    args += [
        "--start",
        "b=1,2,0.5",
        "--listen",
        "a=tls/10.0.0.1:7447",
        "--listen",
        "b=tls/10.0.0.2:7447",
    ]
    assert main(args) == 0
    c = load_agent_config(tmp_path / "c" / "robots" / "b" / "agent.toml", "b")
    assert c.start == (1.0, 2.0, 0.5)
    assert c.zenoh.document()["connect"]["endpoints"] == ["tls/10.0.0.1:7447"]
    cert = _cert(tmp_path / "c" / "robots" / "b" / "tls.pem")
    names = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert "10.0.0.2" in {str(ip) for ip in names.get_values_for_type(x509.IPAddress)}


# -- the merge rule -----------------------------------------------------------------------------


def _json5(tmp_path: Path, doc: dict[str, object]) -> Path:
    path = tmp_path / "z.json5"
    path.write_text("// a comment, as JSON5 allows\n" + json.dumps(doc))
    return path


def test_a_field_given_in_both_places_must_agree(tmp_path: Path) -> None:
    path = _json5(tmp_path, {"scouting": {"gossip": {"enabled": False}},
                             "listen": {"endpoints": ["tcp/127.0.0.1:17700"]}})  # fmt: skip
    with pytest.raises(ZenohConfigError, match="scouting/gossip/enabled is false but the settings"):
        ZenohSettings(gossip=True, config_file=path).document()
    with pytest.raises(ZenohConfigError, match="listen/endpoints"):
        ZenohSettings(listen=("tcp/127.0.0.1:17701",), config_file=path).document()
    # left out: the file's value; given the same: fine
    doc = ZenohSettings(config_file=path).document()
    assert doc["scouting"]["gossip"]["enabled"] is False
    assert doc["listen"]["endpoints"] == ["tcp/127.0.0.1:17700"]
    same = ZenohSettings(gossip=False, listen=("tcp/127.0.0.1:17700",), config_file=path)
    assert same.document()["transport"]["link"]["tx"]["lease"] == 3000  # default fills the rest


def test_a_json5_file_cannot_turn_multicast_scouting_on_and_must_parse(tmp_path: Path) -> None:
    path = _json5(tmp_path, {"scouting": {"multicast": {"enabled": True}}})
    with pytest.raises(ZenohConfigError, match="multicast"):
        ZenohSettings(config_file=path).document()
    path.write_text("{ not json5")
    with pytest.raises(ZenohConfigError, match="not JSON5"):
        ZenohSettings(config_file=path).document()


def test_an_exposed_agent_without_mutual_tls_runs_only_when_it_says_insecure(
    tmp_path: Path,
) -> None:
    (tmp_path / "model.toml").write_text(dump_robot_model(load_scenario("paper").robot_model()))
    base = '[agent]\nmodel = "model.toml"\nstart = [0, 0, 0]\nroster = ["r1"]\n[zenoh]\n'
    path = tmp_path / "agent.toml"
    path.write_text(base + 'listen = ["tcp/192.0.2.7:7447"]\n')
    with pytest.raises(AgentConfigError) as err:
        load_agent_config(path, "r1")
    assert err.value.field == "zenoh.insecure" and "192.0.2.7" in str(err.value)
    path.write_text(base + 'listen = ["tcp/192.0.2.7:7447"]\ninsecure = true\n')
    assert load_agent_config(path, "r1").zenoh.off_loopback() == ["tcp/192.0.2.7:7447"]
    path.write_text(base + 'listen = ["tcp/127.0.0.1:7447"]\n')
    assert load_agent_config(path, "r1").zenoh.off_loopback() == []


def test_router_refuses_an_exposed_endpoint_without_mutual_tls_and_needs_a_listen_endpoint(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["router", "--listen", "tcp/192.0.2.7:7447"]) == 2
    assert "not on loopback" in capsys.readouterr().err
    assert main(["router", "--connect", "tcp/127.0.0.1:7447"]) == 2
    assert "needs a listen endpoint" in capsys.readouterr().err
    assert main(["router", "--config", str(tmp_path / "missing.json5")]) == 2
    assert "no such file" in capsys.readouterr().err
    conflict = _json5(tmp_path, {"listen": {"endpoints": ["tcp/127.0.0.1:17702"]}})
    assert main(["router", "--config", str(conflict), "--listen", "tcp/127.0.0.1:17703"]) == 2
    assert "listen/endpoints" in capsys.readouterr().err


def test_fleet_init_routers_dial_the_routers_before_them(tmp_path: Path) -> None:
    args = ["fleet", "init", "--fleet", "lab", "--robots", "r1,r2", "--scenario", "paper",
            "--router", "a=tls/127.0.0.1:17710", "--router", "b=tls/127.0.0.1:17711",
            "--connect", "r2=tls/127.0.0.1:17711", "-o", str(tmp_path / "f")]  # fmt: skip
    assert main(args) == 0
    b = ZenohSettings(config_file=tmp_path / "f" / "routers" / "b" / "zenoh.json5", mode="router")
    assert b.document()["connect"]["endpoints"] == ["tls/127.0.0.1:17710"]
    assert b.document()["mode"] == "router" and b.mutual_tls()
    r2 = load_agent_config(tmp_path / "f" / "robots" / "r2" / "agent.toml", "r2")
    assert r2.zenoh.document()["connect"]["endpoints"] == ["tls/127.0.0.1:17711"]


def test_hostile_security_files_are_one_line_errors(fleet: Path, tmp_path: Path) -> None:
    deep = tmp_path / "deep.json5"
    deep.write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(ZenohConfigError, match="not JSON5"):
        ZenohSettings(config_file=deep).document()
    folder = tmp_path / "r1"
    shutil.copytree(fleet / "robots" / "r1", folder)
    (folder / "signing.key").write_text(
        "-----BEGIN PRIVATE KEY-----\nAAAA\n-----END PRIVATE KEY-----\n"
    )
    with pytest.raises(AgentConfigError) as err:
        load_agent_config(folder / "agent.toml", "r1")
    assert err.value.field == "security.signing_key"
    shutil.copy(fleet / "robots" / "r2" / "signing.key", folder / "signing.key")
    with pytest.raises(AgentConfigError, match="not the key"):  # another robot's key
        load_agent_config(folder / "agent.toml", "r1")
    shutil.copy(fleet / "robots" / "r1" / "tls.key", folder / "signing.key")
    with pytest.raises(AgentConfigError, match="not an Ed25519 key"):  # the TLS key (ECDSA)
        load_agent_config(folder / "agent.toml", "r1")
    (folder / "roster.toml").write_text('fleet = "lab"\n[robots.r1]\nsigning_key = "%%%"\n')
    shutil.copy(fleet / "robots" / "r1" / "signing.key", folder / "signing.key")
    with pytest.raises(AgentConfigError, match="not a base64"):
        load_agent_config(folder / "agent.toml", "r1")
    # A key of small order (here the identity) would "verify" a forged signature of anything.
    roster = tomllib.loads((fleet / "robots" / "r1" / "roster.toml").read_text())
    identity = base64.b64encode((1).to_bytes(32, "little")).decode()
    roster["robots"]["r2"]["signing_key"] = identity
    (folder / "roster.toml").write_text(tomli_w.dumps(roster))
    with pytest.raises(AgentConfigError, match="small order") as err:
        load_agent_config(folder / "agent.toml", "r1")
    assert "r2" in str(err.value)
