{{/*
The chart name, overridable with nameOverride.
*/}}
{{- define "dray.name" -}}
{{- default .Chart.Name .Values.nameOverride | trunc 63 | trimSuffix "-" }}
{{- end }}

{{/*
A fully qualified app name: RELEASE-dray unless the release name already contains the
chart name. At most 40 characters, so that "-coordinator" still makes a DNS label and the
workers' StatefulSet name ("-workers") stays within the 52 characters its pods' revision
label allows.
*/}}
{{- define "dray.fullname" -}}
{{- if .Values.fullnameOverride }}
{{- .Values.fullnameOverride | trunc 40 | trimSuffix "-" }}
{{- else }}
{{- $name := default .Chart.Name .Values.nameOverride }}
{{- if contains $name .Release.Name }}
{{- .Release.Name | trunc 40 | trimSuffix "-" }}
{{- else }}
{{- printf "%s-%s" .Release.Name $name | trunc 40 | trimSuffix "-" }}
{{- end }}
{{- end }}
{{- end }}

{{/*
chart-name-version, for the helm.sh/chart label.
*/}}
{{- define "dray.chart" -}}
{{- printf "%s-%s" .Chart.Name .Chart.Version | replace "+" "_" | trunc 63 | trimSuffix "-" }}
{{- end }}

{{/*
Labels of every object (Helm's recommended app.kubernetes.io/* set). Call with
(dict "ctx" $ "component" "coordinator").
*/}}
{{- define "dray.labels" -}}
helm.sh/chart: {{ include "dray.chart" .ctx }}
{{ include "dray.selectorLabels" . }}
app.kubernetes.io/version: {{ .ctx.Chart.AppVersion | quote }}
app.kubernetes.io/managed-by: {{ .ctx.Release.Service }}
app.kubernetes.io/part-of: dray
{{- end }}

{{/*
Selector labels: stable across upgrades (never the version).
*/}}
{{- define "dray.selectorLabels" -}}
app.kubernetes.io/name: {{ include "dray.name" .ctx }}
app.kubernetes.io/instance: {{ .ctx.Release.Name }}
{{- with .component }}
app.kubernetes.io/component: {{ . }}
{{- end }}
{{- end }}

{{/*
Object names.
*/}}
{{- define "dray.coordinator.fullname" -}}
{{- printf "%s-coordinator" (include "dray.fullname" .) }}
{{- end }}

{{- define "dray.workers.fullname" -}}
{{- printf "%s-workers" (include "dray.fullname" .) }}
{{- end }}

{{/*
The work directory's claim: an existing one, one the chart creates, or none (mode
"fetch" only: the coordinator's work directory is then an emptyDir).
*/}}
{{- define "dray.stateDir.claimName" -}}
{{- if .Values.stateDir.existingClaim }}
{{- .Values.stateDir.existingClaim }}
{{- else if .Values.stateDir.create }}
{{- printf "%s-state" (include "dray.fullname" .) }}
{{- end }}
{{- end }}

{{- define "dray.workDir.claimName" -}}
{{- if .Values.workDir.existingClaim }}
{{- .Values.workDir.existingClaim }}
{{- else if .Values.workDir.create }}
{{- printf "%s-work" (include "dray.fullname" .) }}
{{- else if eq .Values.workDir.mode "shared" }}
{{- fail "workDir: mode \"shared\" needs workDir.existingClaim (a ReadWriteMany claim) or workDir.create=true: the coordinator and the workers share job packages there (or use mode \"fetch\")" }}
{{- end }}
{{- end }}

{{/*
Whether the workers read job packages from the shared work directory (and the scenes
volume) rather than fetching them from the coordinator.
*/}}
{{- define "dray.workDir.shared" -}}
{{- if eq .Values.workDir.mode "shared" }}true{{ end }}
{{- end }}

{{- define "dray.serviceAccountName" -}}
{{- if .Values.serviceAccount.create }}
{{- default (include "dray.fullname" .) .Values.serviceAccount.name }}
{{- else }}
{{- default "default" .Values.serviceAccount.name }}
{{- end }}
{{- end }}

{{/*
The image reference: repository:tag, the tag defaulting to the chart's appVersion.
*/}}
{{- define "dray.image" -}}
{{- printf "%s:%s" .Values.image.repository (default .Chart.AppVersion .Values.image.tag) }}
{{- end }}

{{/*
The coordinator's address as the workers dial it (the Service's cluster DNS name).
*/}}
{{- define "dray.coordinator.url" -}}
{{- printf "http://%s.%s.svc:%d" (include "dray.coordinator.fullname" .) .Release.Namespace (int .Values.coordinator.port) }}
{{- end }}

{{/*
Volumes of a pod, given (dict "ctx" $ "component" "coordinator"|"worker"): /tmp, the work
directory and the scenes. The coordinator mounts them all; a worker mounts the work
directory and the scenes at the same paths only with workDir.mode "shared" (it reads job
packages in place), and otherwise has its own package cache (it fetches them).
*/}}
{{- define "dray.volumes" -}}
{{- $ctx := .ctx }}
{{- $mounts := or (eq .component "coordinator") (include "dray.workDir.shared" $ctx) -}}
- name: tmp
  emptyDir: {}
{{- if eq .component "coordinator" }}
# The job store (--state-dir): the coordinator's alone.
- name: state
{{- with include "dray.stateDir.claimName" $ctx }}
  persistentVolumeClaim:
    claimName: {{ . }}
{{- else }}
  emptyDir: {}
{{- end }}
{{- end }}
{{- if $mounts }}
- name: work
{{- with include "dray.workDir.claimName" $ctx }}
  persistentVolumeClaim:
    claimName: {{ . }}
{{- else }}
  emptyDir: {}
{{- end }}
{{- if eq $ctx.Values.scenes.source "pvc" }}
- name: scenes
  persistentVolumeClaim:
    claimName: {{ required "scenes.pvc.claimName is required when scenes.source is pvc" $ctx.Values.scenes.pvc.claimName }}
    readOnly: true
{{- else if eq $ctx.Values.scenes.source "none" }}
# Procedural scenes only: an empty scene root (the coordinator wants it to exist).
- name: scenes
  emptyDir: {}
{{- end }}
{{- else }}
# Scene packages fetched from the coordinator (dray.v1.PackageService).
- name: package-cache
  emptyDir:
    {{- with $ctx.Values.workers.packageCacheSizeLimit }}
    sizeLimit: {{ . }}
    {{- else }} {}
    {{- end }}
{{- end }}
{{- end }}

{{- define "dray.volumeMounts" -}}
{{- $ctx := .ctx }}
{{- $mounts := or (eq .component "coordinator") (include "dray.workDir.shared" $ctx) -}}
- name: tmp
  mountPath: /tmp
{{- if eq .component "coordinator" }}
- name: state
  mountPath: {{ $ctx.Values.stateDir.path }}
{{- end }}
{{- if $mounts }}
- name: work
  mountPath: {{ $ctx.Values.workDir.path }}
{{- if eq $ctx.Values.scenes.source "pvc" }}
- name: scenes
  mountPath: {{ $ctx.Values.scenes.path }}
  readOnly: true
  {{- with $ctx.Values.scenes.pvc.subPath }}
  subPath: {{ . }}
  {{- end }}
{{- else if eq $ctx.Values.scenes.source "none" }}
- name: scenes
  mountPath: {{ $ctx.Values.scenes.path }}
  readOnly: true
{{- end }}
{{- else }}
- name: package-cache
  mountPath: {{ include "dray.packageCache.path" $ctx }}
{{- end }}
{{- end }}

{{/*
Where a worker keeps fetched scene packages (workDir.mode "fetch").
*/}}
{{- define "dray.packageCache.path" -}}
/var/cache/dray/packages
{{- end }}

{{/*
A gRPC health probe (grpc.health.v1, the server's overall status) on `port`, with the
timings of `probe`. Call with (dict "port" 50051 "probe" .Values.coordinator.livenessProbe).
*/}}
{{- define "dray.grpcProbe" -}}
grpc:
  port: {{ .port }}
initialDelaySeconds: {{ .probe.initialDelaySeconds }}
periodSeconds: {{ .probe.periodSeconds }}
timeoutSeconds: {{ .probe.timeoutSeconds }}
failureThreshold: {{ .probe.failureThreshold }}
{{- end }}

{{/*
Where the auth Secret's token files are mounted.
*/}}
{{- define "dray.auth.path" -}}
/etc/dray/auth
{{- end }}

{{/*
The environment of a pod, given (dict "ctx" $ "component" "coordinator"|"worker"): its
name and namespace (for $(VAR) expansion in the arguments, and the telemetry resource),
the token files of auth.existingSecret (the API token for the coordinator only), and the
OTLP endpoint.
*/}}
{{- define "dray.env" -}}
{{- $ctx := .ctx }}
- name: POD_NAME
  valueFrom:
    fieldRef:
      fieldPath: metadata.name
- name: POD_NAMESPACE
  valueFrom:
    fieldRef:
      fieldPath: metadata.namespace
{{- if $ctx.Values.auth.existingSecret }}
- name: DRAY_CLUSTER_TOKEN_FILE
  value: {{ printf "%s/cluster.token" (include "dray.auth.path" $ctx) | quote }}
{{- if eq .component "coordinator" }}
- name: DRAY_AUTH_TOKEN_FILE
  value: {{ printf "%s/api.token" (include "dray.auth.path" $ctx) | quote }}
{{- end }}
{{- end }}
{{- with $ctx.Values.otlp.endpoint }}
- name: OTEL_EXPORTER_OTLP_ENDPOINT
  value: {{ . | quote }}
- name: OTEL_RESOURCE_ATTRIBUTES
  value: "k8s.pod.name=$(POD_NAME),k8s.namespace.name=$(POD_NAMESPACE)"
{{- end }}
{{- end }}

{{/*
The auth Secret as a read-only volume of token files (none without auth.existingSecret),
given (dict "ctx" $ "component" ...): workers get the cluster token only.
*/}}
{{- define "dray.auth.volume" -}}
{{- $ctx := .ctx }}
{{- with $ctx.Values.auth.existingSecret }}
- name: auth
  secret:
    secretName: {{ . }}
    # Readable by the pod's group (fsGroup), not by others.
    defaultMode: 0440
    items:
      - key: {{ $ctx.Values.auth.clusterTokenKey }}
        path: cluster.token
      {{- if eq $.component "coordinator" }}
      - key: {{ $ctx.Values.auth.apiTokenKey }}
        path: api.token
      {{- end }}
{{- end }}
{{- end }}

{{- define "dray.auth.volumeMount" -}}
{{- if .Values.auth.existingSecret }}
- name: auth
  mountPath: {{ include "dray.auth.path" . }}
  readOnly: true
{{- end }}
{{- end }}
