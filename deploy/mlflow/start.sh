#!/bin/sh
# Start the MLflow server with basic authentication; secrets come from the environment only.
set -eu
: "${MLFLOW_ADMIN_PASSWORD:?}" "${MLFLOW_FLASK_SERVER_SECRET_KEY:?}" "${POSTGRES_PASSWORD:?}"
config=/tmp/basic_auth.ini   # inside the container, never in the image or in git
umask 077
cat > "$config" <<INI
[mlflow]
default_permission = READ
database_uri = postgresql://mlflow:${POSTGRES_PASSWORD}@postgres:5432/mlflow
admin_username = admin
admin_password = ${MLFLOW_ADMIN_PASSWORD}
authorization_function = mlflow.server.auth:authenticate_request_basic_auth
INI
export MLFLOW_AUTH_CONFIG_PATH="$config"
exec mlflow server \
  --app-name basic-auth \
  --backend-store-uri "postgresql://mlflow:${POSTGRES_PASSWORD}@postgres:5432/mlflow" \
  --artifacts-destination s3://mlflow-artifacts \
  --serve-artifacts \
  --host 0.0.0.0 --port 5000 --workers 2
