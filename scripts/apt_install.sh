# apt_install WARNING PACKAGE...: install Debian packages with apt-get (as root), sourced by scripts/setup.sh.
# Waits up to APT_LOCK_TIMEOUT seconds (default 120) for another apt or dpkg holding the lock (an unattended
# upgrade on a fresh machine) instead of failing at once; when apt fails anyway, prints "warning: WARNING" and
# then apt's own reason (its E:/W: lines, else its last lines) on stderr, and returns non-zero.
apt_install() {
  local warning=$1 log status=0
  shift
  log=$(mktemp)
  local lock=(-o "DPkg::Lock::Timeout=${APT_LOCK_TIMEOUT:-120}")
  apt-get "${lock[@]}" update -qq >"$log" 2>&1 \
    && DEBIAN_FRONTEND=noninteractive apt-get "${lock[@]}" install -y -qq --no-install-recommends "$@" >>"$log" 2>&1 \
    || status=$?
  if [ "$status" != 0 ]; then
    echo "warning: $warning" >&2
    if grep -qE '^(E|W|Err):' "$log"; then
      grep -E '^(E|W|Err):' "$log" | tail -n 5 | sed 's/^/  apt-get: /' >&2
    else
      tail -n 5 "$log" | sed 's/^/  apt-get: /' >&2
    fi
  fi
  rm -f "$log"
  return "$status"
}
