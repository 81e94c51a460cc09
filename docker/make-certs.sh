#!/usr/bin/env bash
# Make a test/lab PKI for docker/compose.secure.yaml: a CA and one certificate per role, in
# docker/certs/ (or the folder given). Production deployments use their own CA; what matters
# to evcal is the common name (CN) of each certificate, which names its role in the router's
# access control (docker/zenoh/secure/router.json5):
#   router (also valid for the host names below), evcal-service, evcal-client,
#   evcal-operator, and evcal-rig-NAME for each rig NAME of EVCAL_RIGS (default rig1; files
#   rig-NAME.pem/.key): a rig's certificate feeds its own cameras only, lab/NAME/**
set -euo pipefail
out="${1:-$(dirname "$0")/certs}"
hosts="${EVCAL_ROUTER_HOSTS:-DNS:router,DNS:localhost,IP:127.0.0.1}"
rigs="${EVCAL_RIGS:-rig1}"
mkdir -p "$out"
cd "$out"
umask 077
if [ ! -f ca.key ]; then
  openssl req -x509 -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes -days 825 \
    -subj "/CN=evcal-ca" -keyout ca.key -out ca.pem
fi
roles="router service client operator"
for rig in $rigs; do
  # the name becomes a key expression chunk in the ACL (lab/NAME/**) and a file name
  if ! [[ "$rig" =~ ^[A-Za-z0-9_.-]+$ ]]; then
    echo "make-certs.sh: rig name '$rig': letters, digits, '_', '.' and '-' only" >&2
    exit 2
  fi
  roles="$roles rig-$rig"
done
for role in $roles; do
  cn="evcal-$role"; [ "$role" = router ] && cn="router"
  [ -f "$role.pem" ] && continue
  openssl req -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes -subj "/CN=$cn" \
    -keyout "$role.key" -out "$role.csr"
  printf "subjectAltName=%s\nbasicConstraints=CA:FALSE\n" "$hosts" > "$role.ext"
  openssl x509 -req -in "$role.csr" -CA ca.pem -CAkey ca.key -CAcreateserial -days 825 \
    -extfile "$role.ext" -out "$role.pem"
  rm -f "$role.csr" "$role.ext"
done
chmod 644 ./*.pem
echo "certificates in $out: ca.pem and <role>.pem/.key for $roles"
