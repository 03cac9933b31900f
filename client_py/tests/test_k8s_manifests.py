"""deploy/k8s/ checked against the Kubernetes API schemas that kubernetes-validate bundles (no
cluster and no network needed), strictly (an unknown field is an error), for the oldest
Kubernetes the deployment docs support and the newest bundled; then for what the schemas cannot
see: the objects refer to each other by the right names, a pod is given the time its drain
takes, the Service is headless and lists ready pods only, and every autoscaler metric can reach
its target by the figures measured in docs/deployment.md ("Autoscaling"). A deliberately broken
copy fails each check, so the checks can fail."""

import pathlib
import re
import shutil

import kubernetes_validate
import pytest
import yaml

REPO = pathlib.Path(__file__).resolve().parents[2]
K8S = REPO / "deploy" / "k8s"
COMPOSE = REPO / "docker" / "compose.yaml"
DEPLOYMENT_DOC = REPO / "docs" / "deployment.md"
# A pod under training load: a full pod's environments stepped at most this often each (a trainer
# steps a vector env as fast as its policy allows, far more often) must reach the CPU target.
MAX_STEPS_PER_S_PER_ENV = 20
N_LANDERS = 3  # The environments the measured figures are of.
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
    optional = sorted((folder / "optional").glob("*.yaml"))
    for path in optional:
        for index, document in enumerate(yaml.safe_load_all(path.read_text())):
            for version in VERSIONS:
                try:
                    kubernetes_validate.validate(document, version, strict=True)
                except kubernetes_validate.ValidationError as error:
                    where = ".".join(str(part) for part in error.path)
                    errors.append(f"optional/{path.name}[{index}] (Kubernetes {version}) {where}: {error.message}")
            if document["kind"] == "HorizontalPodAutoscaler" and "StatefulSet" in by_kind:
                errors += [f"optional/{path.name}: {e}" for e in autoscaling_errors(by_kind["StatefulSet"], document)]
    errors += reference_errors(by_kind)
    if "StatefulSet" in by_kind and "HorizontalPodAutoscaler" in by_kind:
        errors += autoscaling_errors(by_kind["StatefulSet"], by_kind["HorizontalPodAutoscaler"])
    return errors


def measured_figures() -> dict[str, float]:
    """The "used below" column of docs/deployment.md's table of measured figures (Autoscaling):
    cores per 1,000 agent-steps/s, cores per 1,000 idle environments, memory idle (MiB) and per
    environment (KiB)."""
    section = DEPLOYMENT_DOC.read_text().split("### Autoscaling", 1)[1]
    rows = {}
    for line in section.splitlines():
        cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
        if len(cells) == 3 and cells[0] not in ("figure", "---"):
            rows[cells[0]] = float(re.match(r"[\d.,]+", cells[2]).group().replace(",", ""))
    return {
        "cores_per_1000_agent_steps_per_s": rows["CPU per 1,000 agent-steps/s"],
        "cores_per_1000_idle_envs": rows["CPU per 1,000 hosted idle environments"],
        "idle_mib": rows["memory idle"],
        "kib_per_env": rows["memory per hosted environment (3 landers, reset)"],
    }


def _quantity(text: str) -> float:
    """A Kubernetes quantity as a number: cores for CPU ("2", "500m"), MiB for memory ("640Mi",
    "1Gi")."""
    text = str(text)
    for suffix, scale in (("m", 1e-3), ("Mi", 1.0), ("Gi", 1024.0), ("Ki", 1 / 1024)):
        if text.endswith(suffix):
            return float(text[: -len(suffix)]) * scale
    return float(text)


def _flag(flags: list[str], name: str) -> float:
    values = [flag.partition("=")[2].split()[0] for flag in flags if flag.startswith(f"--{name}=")]
    assert values, f"the StatefulSet's server has no --{name}"
    return float(values[-1])


def autoscaling_errors(server: dict, autoscaler: dict) -> list[str]:
    """One line per autoscaler metric that cannot reach its target, by the measured figures: CPU
    must be reached by a full pod whose environments are stepped MAX_STEPS_PER_S_PER_ENV times a
    second each and by a pod whose --threads are busy; memory by a full pod; environments hosted
    below --max_envs. There must be a CPU metric."""
    figures = measured_figures()
    container = server["spec"]["template"]["spec"]["containers"][0]
    flags = container.get("args", [])
    threads, max_envs = _flag(flags, "threads"), _flag(flags, "max_envs")
    requests = container["resources"]["requests"]
    errors = []
    kinds = []
    for metric in autoscaler["spec"].get("metrics", []):
        if metric["type"] == "Resource":
            name, target = metric["resource"]["name"], metric["resource"]["target"]
            kinds.append(name)
            if target.get("type") != "Utilization":
                continue
            share = target["averageUtilization"] / 100
            if name == "cpu":
                target_cores = share * _quantity(requests["cpu"])
                agent_steps = target_cores / figures["cores_per_1000_agent_steps_per_s"] * 1000
                per_env = agent_steps / (max_envs * N_LANDERS)
                if per_env > MAX_STEPS_PER_S_PER_ENV:
                    errors.append(
                        f"the CPU target ({target_cores:g} cores) needs {agent_steps:,.0f} agent-steps/s, a full pod's "
                        f"{max_envs:g} environments stepped {per_env:.1f} times a second each (more than "
                        f"{MAX_STEPS_PER_S_PER_ENV})"
                    )
                if target_cores >= threads:
                    errors.append(
                        f"the CPU target ({target_cores:g} cores) is not below --threads={threads:g}: a pod whose "
                        "worker threads are busy does not reach it"
                    )
            elif name == "memory":
                target_mib = share * _quantity(requests["memory"])
                full_mib = figures["idle_mib"] + max_envs * figures["kib_per_env"] / 1024
                if full_mib < target_mib:
                    errors.append(
                        f"the memory target ({target_mib:g} MiB) can never be reached: a full pod ({max_envs:g} "
                        f"environments) holds {full_mib:.0f} MiB"
                    )
        elif metric["type"] == "Pods" and metric["pods"]["metric"]["name"] == "mll_envs_live":
            value = metric["pods"]["target"].get("averageValue")  # Missing: the schema check says so.
            if value is not None and _quantity(value) >= max_envs:
                errors.append(
                    f"the mll_envs_live target ({value}) is not below --max_envs={max_envs:g}: pods refuse "
                    "environments before reaching it"
                )
    if "cpu" not in kinds:
        errors.append("the HorizontalPodAutoscaler has no CPU metric")
    return errors


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
    if service["spec"].get("publishNotReadyAddresses", False) is not False:
        errors.append("the Service publishes pods that are not ready: its name would resolve to draining pods")
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
        ("service.yaml", "publishNotReadyAddresses: false", "publishNotReadyAddresses: true", "not ready"),
        ("hpa.yaml", "  behavior:", "    - type: Resource\n      resource:\n        name: memory\n        target:\n"
         "          type: Utilization\n          averageUtilization: 80\n  behavior:", "memory target"),  # Never fires.
        ("hpa.yaml", "averageUtilization: 70", "averageUtilization: 150", "not below --threads"),
        ("hpa.yaml", "name: cpu", "name: memory", "no CPU metric"),
        ("statefulset.yaml", "--max_envs=2048", "--max_envs=1024", "stepped 26.8 times a second"),  # Small pods.
        ("optional/hpa-envs-hosted.yaml", 'averageValue: "1536"', 'averageValue: "2048"', "mll_envs_live target"),
        ("optional/hpa-envs-hosted.yaml", "averageValue:", "averageValu:", "optional/hpa-envs-hosted.yaml[0]"),
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
