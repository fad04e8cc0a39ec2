#!/bin/bash
# Container health check without curl: GET http://127.0.0.1:PORT/PATH over bash's /dev/tcp,
# healthy when the status line says 200. Usage: crossview-healthcheck [PORT] [PATH]
set -euo pipefail
port=${1:-8080}
path=${2:-/readyz}
exec 3<>"/dev/tcp/127.0.0.1/${port}"
printf 'GET %s HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\n\r\n' "$path" >&3
read -r -t 3 status_line <&3
[[ "$status_line" == HTTP/1.?\ 200* ]] || { echo "unhealthy: ${status_line:-no answer}" >&2; exit 1; }
