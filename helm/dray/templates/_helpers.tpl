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

{{- define "dray.workDir.claimName" -}}
{{- if .Values.workDir.existingClaim }}
{{- .Values.workDir.existingClaim }}
{{- else if .Values.workDir.create }}
{{- printf "%s-work" (include "dray.fullname" .) }}
{{- else }}
{{- fail "workDir: set workDir.existingClaim (a ReadWriteMany claim) or workDir.create=true: the coordinator and the workers share job packages there" }}
{{- end }}
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
Volumes of the coordinator and the workers: /tmp, the work directory and the scenes,
each mounted at the same path in every pod (workers read job packages in the work
directory and pre-partitioned packages under the scene root at the coordinator's paths).
*/}}
{{- define "dray.volumes" -}}
- name: tmp
  emptyDir: {}
- name: work
  persistentVolumeClaim:
    claimName: {{ include "dray.workDir.claimName" . }}
{{- if eq .Values.scenes.source "pvc" }}
- name: scenes
  persistentVolumeClaim:
    claimName: {{ required "scenes.pvc.claimName is required when scenes.source is pvc" .Values.scenes.pvc.claimName }}
    readOnly: true
{{- else if eq .Values.scenes.source "none" }}
# Procedural scenes only: an empty scene root (the coordinator wants it to exist).
- name: scenes
  emptyDir: {}
{{- end }}
{{- end }}

{{- define "dray.volumeMounts" -}}
- name: tmp
  mountPath: /tmp
- name: work
  mountPath: {{ .Values.workDir.path }}
{{- if eq .Values.scenes.source "pvc" }}
- name: scenes
  mountPath: {{ .Values.scenes.path }}
  readOnly: true
  {{- with .Values.scenes.pvc.subPath }}
  subPath: {{ . }}
  {{- end }}
{{- else if eq .Values.scenes.source "none" }}
- name: scenes
  mountPath: {{ .Values.scenes.path }}
  readOnly: true
{{- end }}
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
