#!/usr/bin/env bash
# Test CA and certificates for quick-stream's TLS + access-control configurations (openssl only).
#
#   deploy/tls/make-certs.sh [--streams ID[,ID...]] [--all-streams-recorder] OUT_DIR [ROUTER_HOST_OR_IP ...]
#
# Writes, for each party, a folder holding only what that process needs: ca.pem, NAME.pem and
# NAME.key (its own key and no other: point --tls-dir at it with --tls-name NAME, or mount its
# files), signed by a test CA whose certificate is also OUT_DIR/ca.pem:
#   OUT_DIR/router/               CN quick-router: the router (subjectAltNames: the given host names / IPs,
#                                 default localhost 127.0.0.1; clients check the name they dial)
#   OUT_DIR/STREAM/SERVICE/       CN quick-SERVICE-STREAM, for every stream of --streams (default cam0) and
#                                 SERVICE capture, flow, motion, render, recorder: one service of one stream
#   OUT_DIR/monitor/              CN quick-monitor: watches every stream (subscribes, sees liveliness tokens)
#   OUT_DIR/recorder/             CN quick-recorder, with --all-streams-recorder: `recorder --all-streams`
# The common names are what the router's access control matches (`quick-stream acl --streams ...`,
# deploy/zenoh/router-tls.json5 for cam0). The CA's private key is deleted once every certificate is
# signed: it never sits in a folder a process is given (re-run the script to issue new certificates).
# A test CA is for tests and labs; use your own PKI in production, with the same common names.
set -euo pipefail
usage="usage: make-certs.sh [--streams ID[,ID...]] [--all-streams-recorder] OUT_DIR [ROUTER_HOST_OR_IP ...]"
streams=cam0
all_recorder=0
while [ $# -gt 0 ]; do
  case $1 in
    --streams) streams=${2:?$usage}; shift 2 ;;
    --streams=*) streams=${1#--streams=}; shift ;;
    --all-streams-recorder) all_recorder=1; shift ;;
    -*) echo "make-certs.sh: unknown option $1; $usage" >&2; exit 2 ;;
    *) break ;;
  esac
done
out=${1:?$usage}
shift || true
hosts=("$@")
[ ${#hosts[@]} -eq 0 ] && hosts=(localhost 127.0.0.1)
IFS=, read -r -a stream_ids <<< "$streams"
[ ${#stream_ids[@]} -gt 0 ] || { echo "make-certs.sh: --streams is empty" >&2; exit 2; }
for s in "${stream_ids[@]}"; do  # stream ids as everywhere (1-64 of [A-Za-z0-9_-]), not a party's folder name
  if ! [[ $s =~ ^[A-Za-z0-9_-]{1,64}$ ]] || [[ $s =~ ^(router|monitor|recorder)$ ]]; then
    echo "make-certs.sh: --streams: stream id must be 1-64 of [A-Za-z0-9_-] and not router, monitor or recorder, got '$s'" >&2
    exit 2
  fi
done
mkdir -p "$out"
out=$(cd "$out" && pwd)
work=$(mktemp -d)  # the CA key and the signing requests: never in OUT_DIR, removed at the end
trap 'rm -rf "$work"' EXIT
cd "$work"
days=825
openssl req -x509 -newkey ec -pkeyopt ec_paramgen_curve:prime256v1 -nodes -keyout ca.key -out ca.pem -days "$days" \
  -subj "/CN=quick-stream test CA" -addext "basicConstraints=critical,CA:TRUE" \
  -addext "keyUsage=critical,keyCertSign,cRLSign" 2>/dev/null
san=""
for h in "${hosts[@]}"; do
  if [[ $h =~ ^[0-9.]+$ ]]; then san+="IP:$h,"; else san+="DNS:$h,"; fi
done
san=${san%,}
make() {  # make DIR NAME CN [SAN]: DIR/NAME.pem, DIR/NAME.key, DIR/ca.pem
  local dir=$1 name=$2 cn=$3 alt=${4:-"DNS:$3"}
  openssl req -newkey ec -pkeyopt ec_paramgen_curve:prime256v1 -nodes -keyout "$name.key" -out "$name.csr" -subj "/CN=$cn" 2>/dev/null
  printf 'basicConstraints=CA:FALSE\nkeyUsage=critical,digitalSignature,keyEncipherment\nextendedKeyUsage=serverAuth,clientAuth\nsubjectAltName=%s\n' \
    "$alt" > "$name.ext"
  openssl x509 -req -in "$name.csr" -CA ca.pem -CAkey ca.key -CAcreateserial -out "$name.pem" -days "$days" \
    -extfile "$name.ext" 2>/dev/null
  rm -f "$name.csr" "$name.ext"
  mkdir -p "$dir"
  cp ca.pem "$dir/ca.pem"
  mv "$name.pem" "$name.key" "$dir/"
  chmod 600 "$dir/$name.key"
}
make "$out/router" router quick-router "$san"
make "$out/monitor" monitor quick-monitor
[ "$all_recorder" = 1 ] && make "$out/recorder" recorder quick-recorder
for s in "${stream_ids[@]}"; do
  for svc in capture flow motion render recorder; do
    make "$out/$s/$svc" "$svc" "quick-$svc-$s"
  done
done
cp ca.pem "$out/ca.pem"
echo "wrote $out: ca.pem, router/, monitor/$([ "$all_recorder" = 1 ] && echo ', recorder/') and per stream" \
  "(${stream_ids[*]}) capture/, flow/, motion/, render/, recorder/ (each: ca.pem, NAME.pem, NAME.key); the CA key is not kept"
