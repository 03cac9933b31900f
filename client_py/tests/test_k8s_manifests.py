"""deploy/k8s/ checked against the Kubernetes API schemas that kubernetes-validate bundles (no
cluster and no network needed), strictly (an unknown field is an error), for the oldest
Kubernetes the deployment docs support and the newest bundled; then for what the schemas cannot
see: the objects refer to each other by the right names, and a pod is given the time its drain
takes. A deliberately broken copy fails each check, so the checks can fail."""

import pathlib
import re
import shutil

import kubernetes_validate
import pytest
import yaml

REPO = pathlib.Path(__file__).resolve().parents[2]
K8S = REPO / "deploy" / "k8s"
COMPOSE = REPO / "docker" / "compose.yaml"
# docs/deployment.md: kubectl 1.27+.
VERSIONS = ("1.27.0", kubernetes_validate.latest_version())
# The server's defaults for the flags that bound how long it takes to stop (mll_server --help).
STOP_FLAG_DEFAULTS = {"drain_s": 0.0, "shutdown_grace_s": 5.0}


def manifest_errors(folder: pathlib.Path) -> list[str]:
    """One line per problem of the manifests in `folder`: schema violations of every document
    of every *.yaml but the kustomization, kustomization resources that are missing or files it
    leaves out, and the inconsistencies reference_errors finds."""
    errors = []
    kustomization = yaml.safe_load((folder / "kustomization.yaml").read_text())
    listed = set(kustomization["resources"])
    manifests = sorted(path for path in folder.glob("*.yaml") if path.name != "kustomization.yaml")
    for name in sorted(listed - {path.name for path in manifests}):
        errors.append(f"kustomization.yaml lists {name}, which does not exist")
    by_kind = {}
    for path in manifests:
        if path.name not in listed:
            errors.append(f"kustomization.yaml does not list {path.name}")
        for index, document in enumerate(yaml.safe_load_all(path.read_text())):
            by_kind[document["kind"]] = document
            for version in VERSIONS:
                try:
                    kubernetes_validate.validate(document, version, strict=True)
                except kubernetes_validate.ValidationError as error:
                    where = ".".join(str(part) for part in error.path)
                    errors.append(f"{path.name}[{index}] (Kubernetes {version}) {where}: {error.message}")
                except kubernetes_validate.SchemaNotFoundError as error:
                    errors.append(f"{path.name}[{index}] (Kubernetes {version}): no schema: {error}")
    return errors + reference_errors(by_kind)


def stop_seconds(flags: list[str]) -> float:
    """How long a server started with `flags` may take to stop after SIGTERM: --drain_s +
    --shutdown_grace_s (the last of a repeated flag wins, as in mll_server)."""
    seconds = dict(STOP_FLAG_DEFAULTS)
    for flag in flags:
        name, _, value = flag.removeprefix("--").partition("=")
        if name in seconds:
            seconds[name] = float(value)
    return sum(seconds.values())


def reference_errors(by_kind: dict[str, dict]) -> list[str]:
    """One line per inconsistency between the objects (kind -> document): the StatefulSet must be
    governed by the headless Service (its per-pod DNS names come from it), the Service, the
    PodDisruptionBudget and the StatefulSet must select its pods, the HorizontalPodAutoscaler
    must scale it, and its grace period must outlast the server's drain and shutdown grace."""
    kinds = ("StatefulSet", "Service", "HorizontalPodAutoscaler", "PodDisruptionBudget")
    missing = [f"no {kind} among the manifests" for kind in kinds if kind not in by_kind]
    if missing:
        return missing
    server, service, autoscaler, budget = (by_kind[kind] for kind in kinds)
    errors = []
    if server["spec"].get("serviceName") != service["metadata"]["name"]:
        errors.append(
            f"the StatefulSet's serviceName {server['spec'].get('serviceName')!r} is not "
            f"the Service's name {service['metadata']['name']!r}"
        )
    if service["spec"].get("clusterIP") != "None":
        errors.append("the Service is not headless (clusterIP: None): no per-pod DNS names")
    pod_labels = server["spec"]["template"]["metadata"]["labels"]
    selectors = {
        "Service": service["spec"].get("selector", {}),
        "PodDisruptionBudget": budget["spec"]["selector"]["matchLabels"],
        "StatefulSet": server["spec"]["selector"]["matchLabels"],
    }
    for kind, selector in selectors.items():
        if not selector or not selector.items() <= pod_labels.items():
            errors.append(f"the {kind}'s selector {selector} does not select the pods {pod_labels}")
    target = autoscaler["spec"]["scaleTargetRef"]
    scaled = (target["apiVersion"], target["kind"], target["name"])
    if scaled != (server["apiVersion"], server["kind"], server["metadata"]["name"]):
        errors.append(f"the HorizontalPodAutoscaler's scaleTargetRef {scaled} is not the StatefulSet")
    pod = server["spec"]["template"]["spec"]
    grace = pod.get("terminationGracePeriodSeconds", 30)  # Kubernetes' default.
    stop = stop_seconds(pod["containers"][0].get("args", []))
    if grace <= stop:
        errors.append(
            f"terminationGracePeriodSeconds {grace} does not outlast --drain_s + "
            f"--shutdown_grace_s = {stop:g} s: the drain would be cut short by SIGKILL"
        )
    return errors


def test_manifests_match_the_kubernetes_schemas_and_each_other():
    assert manifest_errors(K8S) == []


def test_compose_gives_the_server_the_time_its_drain_takes():
    server = yaml.safe_load(COMPOSE.read_text())["services"]["server"]
    minutes, seconds = re.fullmatch(r"(?:(\d+)m)?(?:(\d+)s)?", server["stop_grace_period"]).groups()
    grace = 60 * int(minutes or 0) + int(seconds or 0)
    assert grace > stop_seconds(server["command"])


@pytest.mark.parametrize(
    "file, old, new, expected",
    [
        ("statefulset.yaml", "terminationGracePeriodSeconds:", "terminationGracePeriod:", "terminationGracePeriod"),  # Misspelt field.
        ("statefulset.yaml", "containerPort: 50051", "containerPort: fifty", "containerPort"),  # Wrong type.
        ("statefulset.yaml", "podManagementPolicy: Parallel", "podManagementPolicy: 7", "podManagementPolicy"),  # Wrong type.
        ("service.yaml", "kind: Service", "kind: Servize", "no schema"),  # Unknown kind.
        ("kustomization.yaml", "- pdb.yaml", "- pdbs.yaml", "pdbs.yaml"),  # Dangling resource.
        ("statefulset.yaml", "serviceName: mll-server", "serviceName: mll", "serviceName 'mll'"),  # No per-pod DNS.
        ("service.yaml", "clusterIP: None", "clusterIP: 10.0.0.9", "not headless"),
        ("pdb.yaml", "      app.kubernetes.io/name: mll-server", "      app.kubernetes.io/name: mll", "PodDisruptionBudget's selector"),  # Selects nothing.
        ("hpa.yaml", "kind: StatefulSet", "kind: Deployment", "scaleTargetRef"),  # Scales another object.
        ("statefulset.yaml", "--drain_s=15", "--drain_s=25", "terminationGracePeriodSeconds 30"),  # Drain cut short.
    ],
)
def test_a_broken_manifest_fails(tmp_path, file, old, new, expected):
    broken = tmp_path / "k8s"
    shutil.copytree(K8S, broken)
    text = (broken / file).read_text()
    assert old in text, f"{file} no longer has {old!r}; update this test"
    (broken / file).write_text(text.replace(old, new, 1))
    errors = manifest_errors(broken)
    assert errors and any(expected in error for error in errors), errors
