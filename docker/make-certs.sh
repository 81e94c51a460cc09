#!/usr/bin/env bash
# Make a test/lab PKI for docker/compose.secure.yaml: a CA and one certificate per role, in
# docker/certs/ (or the folder given). Production deployments use their own CA; what matters
# to evcal is the common name (CN) of each certificate, which names its role in the router's
# access control (docker/zenoh/secure/router.json5):
#   router (also valid for the host names below), evcal-rig, evcal-service, evcal-client,
#   evcal-operator
set -euo pipefail
out="${1:-$(dirname "$0")/certs}"
hosts="${EVCAL_ROUTER_HOSTS:-DNS:router,DNS:localhost,IP:127.0.0.1}"
mkdir -p "$out"
cd "$out"
umask 077
if [ ! -f ca.key ]; then
  openssl req -x509 -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes -days 825 \
    -subj "/CN=evcal-ca" -keyout ca.key -out ca.pem
fi
for role in router rig service client operator; do
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
echo "certificates in $out: ca.pem and <role>.pem/.key for router rig service client operator"
