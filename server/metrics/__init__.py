"""What the server measures of itself and how ``/metrics`` shows it: Prometheus text exposition
(``prometheus``), sensor-stamp → live / stored latency histograms (``latency``) and CPU seconds
per thread (``thread_cpu``). Imports nothing of the API: the runtime hands metric families up."""
